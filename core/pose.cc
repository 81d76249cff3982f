#include "core/pose.h"

#include <cstdio>

namespace trackcal {

std::string Rigid3d::ToString() const {
  char buf[256];
  std::snprintf(buf, sizeof(buf), "Rigid3d(rotation_xyzw=[%.9g, %.9g, %.9g, %.9g], translation=[%.9g, %.9g, %.9g])",
                rotation.x(), rotation.y(), rotation.z(), rotation.w(), translation.x(),
                translation.y(), translation.z());
  return buf;
}

}  // namespace trackcal
