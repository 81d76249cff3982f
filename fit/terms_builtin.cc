// Registers the term types of fit/ itself: polynomial, lut and the physical effects.
#include "fit/model_file.h"
#include "fit/terms_lut.h"
#include "fit/terms_physical.h"
#include "fit/terms_polynomial.h"

namespace trackcal::fit {

void RegisterBuiltinTerms(TermRegistry* registry) {
  registry->Register(PolynomialTerm::kType, &PolynomialTerm::FromYaml);
  registry->Register(LutTerm::kType, &LutTerm::FromYaml);
  RegisterPhysicalTerms(registry);
}

}  // namespace trackcal::fit
