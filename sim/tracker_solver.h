// The tracker's own pose solver: what a Fastrak computes from its signal matrix.
//
// It assumes free space, ideal dipoles with field constant k and an ideal receiver (G = I), so
// S = R^T k D(p). Closed form: S^T S = (k^2 / r^6) (3 u u^T + I), whose trace gives r and whose top
// eigenvector gives u up to sign; the sign is chosen by the hemisphere (u . h >= 0, like the
// Fastrak's `H` command, default H1,0,0: the +x hemisphere). Because (3 u u^T - I)^-1 =
// 1.5 u u^T - I, R^T = S (r^3 / k) (1.5 u u^T - I), projected onto SO(3). Levenberg-Marquardt then
// refines (p, R) to the least-squares fit of S to R^T k D(p), which for distorted data is what a
// real tracker reports: a pose that explains the measured signal as a free-space one.
// D(-p) = D(p): the solver cannot tell p from -p, which is why the hemisphere exists.

#pragma once

#include <Eigen/Core>

#include "core/pose.h"
#include "sim/field.h"

namespace trackcal::sim {

struct TrackerSolverOptions {
  double field_constant = 1.0;  // k assumed by the tracker (the free-space model's only parameter)
  Eigen::Vector3d hemisphere_in_transmitter = Eigen::Vector3d::UnitX();  // reported p has p.h >= 0
  int max_iterations = 50;        // Levenberg-Marquardt iterations after the closed form
  double step_tolerance = 1e-12;  // stop when a step is below this times max(1 m, |p|)
  // Throws std::invalid_argument naming the field.
  void Check() const;
};

struct TrackerSolution {
  Rigid3d transmitter_from_receiver;  // reported pose
  Rigid3d closed_form;                // pose before refinement
  double residual_norm = 0.0;         // Frobenius norm of S minus the model's signal at the pose
  int iterations = 0;                 // refinement iterations taken
  bool converged = false;             // refinement met step_tolerance (or was exact)
};

// Recovers the pose from a signal matrix. Returns converged = false when the signal is degenerate
// (not finite, or zero) or refinement ran out of iterations; the pose is then the best found.
TrackerSolution SolveFreeSpacePose(const Eigen::Matrix3d& signal,
                                   const TrackerSolverOptions& options = {});

// The same refinement under a full field model (distortion sources, octupole terms) and receiver
// gain matrix G: the pose whose modelled signal G R^T B(p) best fits `signal`, found by
// Levenberg-Marquardt from `initial` (e.g. the tracker's report). This is the inverse of a physical
// model a runtime correction needs. No hemisphere is imposed: the result stays near `initial`.
// Only max_iterations and step_tolerance of `options` are used; `closed_form` is `initial`.
TrackerSolution SolvePoseInField(const Eigen::Matrix3d& signal, const FieldModel& field,
                                 const Eigen::Matrix3d& receiver_gain_matrix,
                                 const Rigid3d& initial, const TrackerSolverOptions& options = {});

// The true pose whose tracker report, under `field` and `receiver_gain_matrix` and the free-space
// solver of `options`, equals `reported`: the exact inverse of "reported = solver(S(true pose))",
// which a physical-model correction applies at run time. (Rebuilding S from the report and fitting
// the full model to it is not enough: it drops the free-space fit's residual, centimetres in the
// paper room.) Fixed-point iteration x <- x + (reported - report(x)) in position and world-frame
// rotation, from x = reported; it contracts while the distortion's Jacobian is below 1.
// `converged` is false if the correction step is still above `tolerance_m` (and the same in
// radians) after `max_iterations`.
TrackerSolution InvertReportedPose(const Rigid3d& reported, const FieldModel& field,
                                   const Eigen::Matrix3d& receiver_gain_matrix,
                                   const TrackerSolverOptions& options = {},
                                   int max_iterations = 50, double tolerance = 1e-12);

}  // namespace trackcal::sim
