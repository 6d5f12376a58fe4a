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

// What a lower bound on one candidate's NLL needs from its clicks at one
// shift (the NLL of fit_weights with K = 1, alpha free in [0, alpha_max]).
struct ClickSums {
  double mass = 0;               // S: the candidate's on-sensor mass
  double reached = 0;            // clicks with P_c > 0
  double reached_p = 0;          // sum of P_c over them
  double reached_background = 0; // sum of background_c over them
  double unreached_nll = 0;      // sum of -background_c - log(1 - exp(-background_c)) over the others
};
// Over every alpha: with g(x) = -x - log(1 - exp(-x)), convex and falling,
// NLL(alpha) = alpha S + sum_c g(b_c + alpha P_c) >= unreached_nll +
// alpha S + n g(mean b + alpha mean P) (Jensen over the n reached clicks),
// whose minimum over alpha has a closed form. Equal when every reached click
// has the same P and b. Lets a search skip the weight fit of a candidate
// that cannot beat one already fitted (issue 12).
double nll_lower_bound(const ClickSums& c, double alpha_max);

// A start for Newton when a weight has none: the clicks the PSF reaches over
// its on-sensor mass, within [1e-3, alpha_max].
double initial_alpha(std::span<const double> p, double s, double alpha_max);

}  // namespace prism::ref
