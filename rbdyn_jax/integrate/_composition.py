"""Symmetric compositions of a symmetric second-order map, and the exact sub-flows a
composed step runs (docs/physics.md#composition-to-higher-order).

A symmetric map S(h) of order 2 (Strang's splitting) composed as
`S(γ_s h) ∘ … ∘ S(γ_1 h)` with symmetric coefficients (γ_i = γ_{s+1−i}) is again symmetric,
and of order 4 when Σγ = 1 and Σγ³ = 0, of order 6 when moreover Σγ⁵ = 0 and one condition
more holds (Hairer, Lubich & Wanner (2006), §V.3). Where S is a chain of exact flows whose
first and last are one term's (`S = f(c h) ∘ … ∘ f(c h)`), the last flow of one stage and
the first of the next merge into one (the exact flows of a term form a one-parameter group:
f(a) ∘ f(b) = f(a + b)): a composed step is `f(γ_1 c h)`, then for each stage i the flows
between, then `f((γ_i + γ_{i+1}) c h)` (γ_{s+1} = 0) — the same flows in every stage, with
other coefficients, so that the stages run as one loop (`Scheme`).
"""

import typing

# The coefficients γ_1, …, γ_s of each order, with their source.
#
# Order 2: Strang's splitting itself.
STRANG = (1.0,)
# Order 4: McLachlan (1995), the 5-stage symmetric composition with γ1 = 0.28 chosen to make
# the leading error term small (γ2 the root of Σγ³ = 0; its local error is 37× smaller than
# that of Yoshida's (1990) 3-stage triple jump on a linear test problem, measured in
# tests/test_splitting.py).
_M1, _M2 = 0.28, 0.62546642846767004501
MCLACHLAN_4 = (_M1, _M2, 1.0 - 2.0 * (_M1 + _M2), _M2, _M1)
# Order 6: Kahan & Li (1997), the 9-stage symmetric composition "s9odr6a", as printed in
# Hairer, Lubich & Wanner (2006), §V.3.2.
_K = (
    0.39216144400731413927925056,
    0.33259913678935943859974864,
    -0.70624617255763935980996482,
    0.08221359629355080023149045,
)
KAHAN_LI_6 = (*_K, 0.79854399093482996339895035, *reversed(_K))

COMPOSITIONS = {2: STRANG, 4: MCLACHLAN_4, 6: KAHAN_LI_6}


class Scheme(typing.NamedTuple):
    """A composed step: the symmetric map `S(h) = edge(c h) ∘ middle ∘ edge(c h)` (flows
    named by strings, `(name, fraction of h)`, the first to run first; `edge = (name, c)`),
    the composition's coefficients `gammas`, the flow `clock` with which the time advances
    (the one holding t' = 1 in the extended phase space: a kick then sees the time at which
    it acts)."""

    edge: tuple[str, float]
    middle: tuple[tuple[str, float], ...]
    gammas: tuple[float, ...]
    clock: str

    def flows(self) -> list[tuple[str, float, float]]:
        """The flows of one composed step in the order they run, merged at the stages'
        seams, as `(name, coefficient, elapsed)`: run for `coefficient` × the step when
        `elapsed` × the step of the time has passed (the unrolled form of the loop over the
        stages that `_splitting_step.Stepper` runs)."""
        name, c = self.edge
        g = self.gammas
        out, elapsed = [(name, g[0] * c, 0.0)], 0.0
        for i, gi in enumerate(g):
            for flow, fraction in self.middle:
                out.append((flow, gi * fraction, elapsed))
                if flow == self.clock:
                    elapsed += gi * fraction
            following = g[i + 1] if i + 1 < len(g) else 0.0
            out.append((name, (gi + following) * c, elapsed))
        return out


__all__ = ["COMPOSITIONS", "KAHAN_LI_6", "MCLACHLAN_4", "STRANG", "Scheme"]
