// Upper tails of the distributions the fit's tests refer to: the registration's residual-trend
// F test, the candidates' chi-square and Hotelling tests, the pose extraction's bad-fit test.

#pragma once

namespace trackcal::fit {

// P(F >= f) for F distributed as F(d1, d2) (Snedecor); 1 for f <= 0 or NaN. Throws
// std::invalid_argument unless d1 and d2 are finite and > 0.
double FDistributionUpperTail(double f, double d1, double d2);

// P(chi2_dof > x): the upper tail of the chi-square distribution (regularised incomplete gamma).
// Throws std::invalid_argument for dof < 1.
double ChiSquareUpperTail(double x, int dof);

}  // namespace trackcal::fit
