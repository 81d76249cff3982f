// Scalar helpers for code templated on the scalar type (double or ceres::Jet).
#pragma once

#include <type_traits>

namespace trackcal {

// The value part of a scalar: the double itself, or the (recursively) real part `a` of a ceres::Jet.
// Used only for discrete decisions (which LUT cell contains a point), never inside the differentiated
// arithmetic, so derivatives are unaffected.
template <typename T>
double ScalarValue(const T& v) {
  if constexpr (std::is_arithmetic_v<T>) {
    return static_cast<double>(v);
  } else {
    return ScalarValue(v.a);
  }
}

}  // namespace trackcal
