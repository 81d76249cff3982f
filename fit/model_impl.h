// Implementation details of fit/model.h (templates). Not to be included directly.
#pragma once

#include <ceres/dynamic_autodiff_cost_function.h>

#include <vector>

namespace trackcal::fit {
namespace internal {

// Adapts Derived::Apply to DynamicAutoDiffCostFunction: parameter 0 is the input pose, then the bound
// blocks; the 7 "residuals" are the output pose.
template <typename Derived>
struct TermApplyFunctor {
  const Derived* term;
  const StationBinding* binding;
  template <typename T>
  bool operator()(T const* const* parameters, T* output7) const {
    return term->Apply(*binding, parameters + 1, parameters[0], output7);
  }
};

}  // namespace internal

template <typename Derived>
bool AutoDiffModelTerm<Derived>::Evaluate(const StationBinding& binding,
                                          const double* const* block_values,
                                          const AmbientPose& input, bool jacobians,
                                          TermEvaluation* result) const {
  const Derived& self = static_cast<const Derived&>(*this);
  const size_t n = binding.blocks.size();
  if (!jacobians) {
    return self.Apply(binding, block_values, input.data(), result->output.data());
  }
  // Derivatives in chunks of 8: the polynomial's 35 x 3 blocks need a few passes, the LUT one.
  internal::TermApplyFunctor<Derived> functor{&self, &binding};
  ceres::DynamicAutoDiffCostFunction<internal::TermApplyFunctor<Derived>, 8> cost(
      &functor, ceres::DO_NOT_TAKE_OWNERSHIP);
  cost.AddParameterBlock(kAmbientPoseSize);
  std::vector<const double*> parameters;
  parameters.reserve(n + 1);
  parameters.push_back(input.data());
  result->d_output_d_blocks.resize(n);
  std::vector<double*> jacobian_ptrs;
  jacobian_ptrs.reserve(n + 1);
  jacobian_ptrs.push_back(result->d_output_d_input.data());
  for (size_t i = 0; i < n; ++i) {
    const int size = blocks_[static_cast<size_t>(binding.blocks[i])].size();
    cost.AddParameterBlock(size);
    parameters.push_back(block_values[i]);
    result->d_output_d_blocks[i].resize(kAmbientPoseSize, size);
    jacobian_ptrs.push_back(result->d_output_d_blocks[i].data());
  }
  cost.SetNumResiduals(kAmbientPoseSize);
  return cost.Evaluate(parameters.data(), result->output.data(), jacobian_ptrs.data());
}

}  // namespace trackcal::fit
