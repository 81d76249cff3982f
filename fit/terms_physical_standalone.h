// Physical-effect terms estimated with Ceres: the parameters of core/physical_correction.h.
//
// Each term is one physical effect with named parameters that can be free or fixed:
//   - sensor_offset: receiver_from_body (rotation on EigenQuaternionManifold, translation) [m];
//   - receiver_gain: the 3 x 3 receiver matrix G (gains and non-orthogonality). Its overall scale
//     is the gauge of the field constant (S = G R^T k B / k'): k stays fixed, G is free;
//   - dipole: an induced dipole (location [m], polarisability [m^3]); may repeat;
//   - plane: a conducting plane (point [m], unit normal on SphereManifold, attenuation);
//   - near_field: the transmitter octupole coefficient of each coil [m^2].
//
// Residuals live in correction space: for one station the corrected pose x*(theta) (the true
// receiver pose behind the report, the inverse core/ runs at run time, composed with the sensor
// offset) minus the reference pose, whitened by the position and orientation noise. x*(theta)
// solves the tracker's normal equations g(x, theta) = J_y^T vec(S(x; theta) - S_free(y)) = 0 (see
// core/physical_correction.h); its Jacobian comes from the implicit function theorem,
// dx/dtheta = -(dg/dx)^-1 dg/dtheta, with dg/dx and dg/dtheta from ceres::Jet autodiff of the
// same templated field code (core/field.h). The inverse itself runs in double.
#pragma once

#include <ceres/problem.h>

#include <Eigen/Core>
#include <string>
#include <vector>

#include "core/field.h"
#include "core/physical_correction.h"
#include "core/pose.h"
#include "fit/covariance.h"

namespace trackcal::fit {

// One station: what the tracker reported and the reference (body) pose.
struct PhysicalObservation {
  Rigid3d reported;                    // transmitter_from_receiver as reported
  Rigid3d reference;                   // transmitter_from_body from the optical reference
  double position_sigma_m = 0.0;       // this station's noise per axis [m]; 0: the options' value
  double orientation_sigma_rad = 0.0;  // [rad]; 0: the options' value
};

// Which parameters are free. Planes and objects of `initial` beyond the free ones stay fixed.
struct PhysicalFitOptions {
  bool sensor_offset = false;           // fit receiver_from_body
  bool receiver_gain = false;           // fit G (9 entries)
  bool near_field = false;              // fit the octupole coefficients (3)
  std::vector<int> free_objects;        // indices into initial.field.objects to fit
  std::vector<int> free_planes;         // indices into initial.field.planes to fit
  double position_sigma_m = 1e-3;       // whitening: position noise per axis [m]
  double orientation_sigma_rad = 1e-3;  // whitening: orientation noise per axis [rad]
  // Robust loss scale in sigmas (Cauchy); 0 disables. Hemisphere flips are outliers of 1000 sigma.
  double robust_loss_sigmas = 0.0;
  int max_iterations = 100;  // Ceres iterations
  // Throws std::invalid_argument naming the field.
  void Check(const PhysicalCorrection& initial) const;
};

struct PhysicalFitResult {
  bool converged = false;                    // Ceres reported convergence
  PhysicalCorrection model;                  // the fitted correction
  std::vector<std::string> parameter_names;  // e.g. "objects[2].location_in_transmitter.x"
  Eigen::VectorXd values;                    // physical values (quaternions as rotation vectors
                                             // of the change from the initial value) [SI]
  Eigen::VectorXd stddev;                    // standard deviations, same order
  std::vector<IdentifiabilityFlag> flags;    // poorly identifiable parameters
  double final_cost = 0.0;                   // 0.5 sum of squared whitened residuals
  std::string report;                        // Ceres brief report
};

// Fits the free parameters of `initial` to the observations.
PhysicalFitResult FitPhysicalModel(const PhysicalCorrection& initial,
                                   const std::vector<PhysicalObservation>& observations,
                                   const PhysicalFitOptions& options);

}  // namespace trackcal::fit
