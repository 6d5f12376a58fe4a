// Global ambiguity of a source position on the binary sensor: how well the
// clicks it is expected to make are told from those of the most similar
// impostor source at least `min_separation_mm` away, with the impostor's own
// best photon count. The CRLB is a local figure (the curvature of the
// likelihood at the truth); the reconstruction's catastrophic errors are
// global (docs/reconstruction.md "Accuracy": lattice aliases, where the source moved by a
// lenslet-lattice vector times (D + L) / L images almost as it does).
//
// The figure: the Kullback-Leibler divergence of the impostor's click
// distribution from the source's, in nats,
//   D = sum_i [ q0 log(q0 / q1) + (1 - q0) (lambda1 - lambda0) ],
//   q = 1 - exp(-lambda), lambda = dark + alpha P_i,
// the expected log-likelihood ratio per event in favour of the truth, which
// grows with the photons. KL rather than the Chernoff or Bhattacharyya
// exponent because it is what maximum likelihood itself weighs (the mean of
// the log-likelihood ratio that decides between the two), and because its
// minimum over the impostor's photons is the impostor's large-sample fit.
//
// The predicted probability of a catastrophic error, p_confusion: that the
// maximum-likelihood estimate lands at least min_separation_mm (r) from the
// source. Two steps.
//
// Whether an impostor beats the truth on an event: the log-likelihood ratio
// S (impostor over truth) is a sum over pixels of independent two-valued
// terms, with mean -D. P(S >= 0) is taken from the saddlepoint
// (Lugannani-Rice) approximation on S's cumulant generating function, whose
// minimum is the Chernoff exponent. The Gaussian Phi(-D / sqrt(V)), V the
// variance of S, was used before: it is the first term of the same expansion
// and errs far in the tail, where a few pixels separate the two patterns and
// S is skewed.
//
// Where the estimate then lands. An impostor in a basin of its own (a
// lattice alias, a distinct depth) takes the estimate with it. But the
// closest pattern r away is often no basin at all: the truth's own basin,
// flattened along its worst direction (deep, at few photons), seen where
// the search holds it, on the sphere of radius r. Winning against the truth
// there moves the estimate only about halfway (exactly halfway for a
// quadratic log-likelihood: the impostor at d wins when the error along d
// passes d / 2). So an impostor held on the sphere is replaced by the one
// 2r away in the same direction, refined on that sphere, and in the quadratic
// limit p_confusion is then the Gaussian tail of the CRLB beyond r along each
// side of the worst direction. The pairwise comparison at r measured, on
// unifocal-f9 at 50 photons (300 events), the rate of errors beyond r / 2
// (11 beyond 1.5 mm against 7.9 predicted; 2 beyond 3 mm): docs/events-and-sweeps.md
// "Predicted against measured".
//
// p_confusion is the sum over the distinct impostors found, capped at 1 (a
// union bound: the impostors compete with each other too). Assumptions: the
// events come from the model (no mismatch), the impostors are those the
// search tries (below), and both the truth and the impostor would be fitted
// to each event (their extra freedom cancels to first order).
//
// Impostors tried: the lattice aliases out to 2 pitches (18 sites in a hex
// array), the source moved r along the CRLB's weakest direction (either
// way), and moved in depth by +-1, 2 and 4 times r, each with its photons
// fitted (one render each); the best few are then refined continuously in
// (x, y, depth, photons) by Levenberg-Marquardt on D, held at least r from
// the source (on the sphere, in its tangent plane; steps of at most r / 2)
// and inside the scene's volume. `kl` and `impostor_mm` report the closest
// of these, r away or more. Two runs whose renders differ in the last bits
// (the device's float sums) can end the descents at different optima: on a
// rugged sphere near the face of a 3-lenslet row, at 104 or 202 nats; at
// depth 20, D within 2e-3 and p_confusion within a factor of 1.6.
#pragma once
#include <glm/glm.hpp>

#include "host/reconstruct/refine.h"

namespace prism {

// What p_confusion is, written into the journals and sweep states that keep
// it, so that a resume refuses figures of another definition (before
// 2026-11-29: the Gaussian tail of each impostor held at r, none named).
inline constexpr const char* confusion_model = "saddlepoint, impostors on the r-sphere moved to 2r";

struct AmbiguitySettings {
  // An impostor is at least this far from the source (3D): by default the
  // distance beyond which `prism evaluate` calls an error catastrophic, so
  // that p_confusion predicts the rate it measures.
  double min_separation_mm = defaults::catastrophic_error_mm;
  double dark_rate = ReconstructionSettings{}.dark_rate;  // per click-level pixel, as the reconstruction
  int refined = 3;                 // best candidates refined continuously
  int iterations = 20;             // LM steps per refined candidate
};

struct Ambiguity {
  double kl = INFINITY;         // D of the closest impostor found, nats
  glm::dvec3 impostor_mm{NAN};  // its position (x, y, depth)
  double impostor_photons = 0;  // its fitted photons on the sensor
  double p_confusion = 0;       // predicted probability per event that the estimate lands r or more away
  int impostors = 0;            // distinct impostors in the union
};

// D, its variance and the impostor's best photons for two images on the same
// grid; `alpha1` is the start and gets the optimum. The reference
// arithmetic of this file (double, every pixel where either image has light).
struct Divergence {
  double kl = 0, variance = 0;
  double p_wins = 0;  // P(the impostor's likelihood >= the truth's) on an event of the truth's, saddlepoint
};
Divergence divergence(const SourceImage& truth, double alpha0, const SourceImage& impostor, double& alpha1,
                      double dark_rate);

// The ambiguity of a source at theta with `photons` expected on the sensor
// (NaN: the model's own at the scene's emitted photons), with `model` (the
// scene's, on the device or the double reference; make_scene_model).
Ambiguity ambiguity(SourceModel& model, const Scene& scene, const glm::dvec3& theta, double photons,
                    const AmbiguitySettings& settings = {});

}  // namespace prism
