// The binary sensor's likelihood in double precision (paper eqs. 12 and 18;
// DESIGN.md "Reconstruction"): the reference of shaders/common/likelihood.glsl
// and the math of the host's refinement. Sparse form: with K vertices of
// weights alpha_k, PSF values P_kc at the clicks c and on-sensor masses S_k,
//   NLL(alpha) = sum_k alpha_k S_k - sum_c [lambda_c + log(1 - exp(-lambda_c))],
//   lambda_c = background_c + sum_k alpha_k P_kc,
// a sum over the clicks only (the constant sum of the background over all
// pixels left out).
#pragma once
#include <span>
#include <vector>

namespace prism::ref {

// log(1 - exp(-lambda)), finite for every lambda > 0 (log(-expm1(-lambda))).
double log_click(double lambda);
// d2/dlambda2 of -log(1 - exp(-lambda)) = exp(-lambda) / (1 - exp(-lambda))^2,
// as 1 / (4 sinh^2(lambda / 2)).
double click_curvature(double lambda);
// The click weight 1 / (1 - exp(-lambda)): minus the gradient of the NLL's
// click term in lambda, plus one.
double click_weight(double lambda);

// Projected Newton on 0 <= alpha_k <= alpha_max (eq. 18) for the NLL above,
// which is convex in alpha; backtracking (Armijo) keeps each step a descent
// and a relative ridge keeps a singular Hessian (two vertices with the same
// PSF) solvable. p[k] holds P_kc at the clicks; alpha is the start and the
// result. Returns the NLL. At most `max_iterations` Newton steps.
double fit_weights(std::span<const std::vector<double>* const> p, std::span<const double> s,
                   std::span<const double> background, std::vector<double>& alpha, int max_iterations,
                   double alpha_max);

// A lower bound on min over 0 <= alpha <= alpha_max of the one-weight NLL
// above (K = 1, P_c = p[c]) without fitting it: the reference of
// likelihood.glsl's nll_lower_bound, which says how it is made, here from
// the clicks themselves in double.
double nll_lower_bound(std::span<const double> p, double s, std::span<const double> background, double alpha_max);

// A start for Newton when a weight has none: the clicks the PSF reaches over
// its on-sensor mass, within [1e-3, alpha_max].
double initial_alpha(std::span<const double> p, double s, double alpha_max);

}  // namespace prism::ref
