// Global ambiguity of a source position on the binary sensor: how well the
// clicks it is expected to make are told from those of the most similar
// impostor source at least `min_separation_mm` away, with the impostor's own
// best photon count. The CRLB is a local figure (the curvature of the
// likelihood at the truth); the reconstruction's catastrophic errors are
// global (README "Accuracy": lattice aliases, where the source moved by a
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
// The predicted probability of a confusion: the log-likelihood ratio of an
// event is a sum over pixels of independent bounded terms, so nearly Gaussian
// with mean -D and variance V = sum_i q0 (1 - q0) (log(q1 / q0) + lambda1 -
// lambda0)^2; P(impostor k wins against the truth) ~ Phi(-D_k / sqrt(V_k)),
// and p_confusion is the sum over the distinct impostors found, capped at 1
// (a union bound: the impostors compete with each other too). Assumptions:
// the events come from the model (no mismatch), the impostors are those the
// search tries (below), and both the truth and the impostor would be fitted
// to each event (their extra freedom cancels to first order). The Gaussian
// tail is optimistic far out (p below ~1e-4), where the Chernoff bound is the
// honest figure; rates that small are not measurable by `prism evaluate`
// either.
//
// Impostors tried: the lattice aliases out to 2 pitches (18 sites in a hex
// array) and the source moved in depth by +-1, 2 and 4 times the separation,
// each with its photons fitted (one render each); the best few are then
// refined continuously in (x, y, depth, photons) by Levenberg-Marquardt on D,
// held at least min_separation_mm from the source and inside the scene's
// volume.
#pragma once
#include <glm/glm.hpp>

#include "host/reconstruct/refine.h"

namespace prism {

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
  double p_confusion = 0;       // predicted probability that an impostor beats the truth, per event
  int impostors = 0;            // distinct impostors in the union
};

// D, its variance and the impostor's best photons for two images on the same
// grid; `alpha1` is the start and gets the optimum. The reference
// arithmetic of this file (double, every pixel where either image has light).
struct Divergence {
  double kl = 0, variance = 0;
};
Divergence divergence(const SourceImage& truth, double alpha0, const SourceImage& impostor, double& alpha1,
                      double dark_rate);

// The ambiguity of a source at theta with `photons` expected on the sensor
// (NaN: the model's own at the scene's emitted photons), with `model` (the
// scene's, on the device or the double reference; make_scene_model).
Ambiguity ambiguity(SourceModel& model, const Scene& scene, const glm::dvec3& theta, double photons,
                    const AmbiguitySettings& settings = {});

}  // namespace prism
