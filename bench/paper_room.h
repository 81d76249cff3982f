// The paper room the physical benchmarks correct in (bench_physical, vrpn_e2e_latency_bench):
// the transmitter's octupole, the floor and the door as planes, three CRTs, the workbench frame and
// the toolbox as induced dipoles (the paper preset's sources, sim/scenes/paper.yaml), and a skewed
// receiver gain. One definition, so both benchmarks time the same model.

#pragma once

#include <Eigen/Core>

#include "core/field.h"

namespace trackcal {

inline FieldModel PaperRoomField() {
  FieldModel field;
  field.transmitter_octupole_m2 = Eigen::Vector3d(-0.000675, -0.0006, -0.00075);
  field.planes.push_back({"floor", Eigen::Vector3d(0, 0, 0.8), Eigen::Vector3d(0, 0, 1), 0.27});
  field.planes.push_back({"door", Eigen::Vector3d(0, -2.1, 0), Eigen::Vector3d(0, 1, 0), 0.18});
  field.objects.push_back({"crt1", Eigen::Vector3d(1.6, 1.0, -0.5), 0.04});
  field.objects.push_back({"crt2", Eigen::Vector3d(0.5, 1.8, -0.5), 0.04});
  field.objects.push_back({"crt3", Eigen::Vector3d(-1.5, 1.2, -0.4), 0.04});
  field.objects.push_back({"frame", Eigen::Vector3d(0.5, 0.0, 0.35), -0.009});
  field.objects.push_back({"toolbox", Eigen::Vector3d(0.6, 0.95, -0.5), 0.002});
  return field;
}

inline Eigen::Matrix3d PaperRoomGain() {
  Eigen::Matrix3d g;
  g << 1.03, 0.01, -0.02, 0.0, 0.97, 0.015, 0.01, -0.01, 1.01;
  return g;
}

}  // namespace trackcal
