"""What a pass scatter allows at best: the stress campaigns' plates with everything known but the pass's own draw.

Run from the project root:  .venv/bin/python benchmarks/bench_forming_frontier.py --seeds 0 1 ... 59
                            [--scatters 0.1 0.2] [--risks 0.0002 0.001]

For each plate of the mixed stress campaigns (``campaign.stress_plates("mixed", 20, seed)``: the
plates of the model, 0.2 mm scatter, hardening and geometry cases) at its hidden yield factor, on
issue 14's machine (compliance 2 mm/MN, the model's geometry), the displacement band ``b_d``: the
tolerance band over the slope of the final curvature in the setting at the target. An advice that
knew the plate, the machine and the scatter ``s`` exactly, the old peak placed to the micron, would
still face each pass's own draw ``N(0, s^2)`` in displacement: the best case of any advice.

- *The aim as it is*: median at the target, or short of it so that 0.5 % ends past 0.8 of the band
  (normal tails: the scatter known); its risk past the verdict's edge (0.95 of the band), summed
  over the plates as the expected over-bent plates of one such pass each; the mean passes a plate
  (the probe's included) should each pass after it be aimed so until the plate is within the band.
- *A risk ``e`` past the verdict's edge*: median at the target or at ``0.95 b_d - z_e s``; the
  probability that the plate is not within the verdict's band after three such passes after its
  probe (each pass a fresh draw at the same aim, rolled while the plate is short; the plate keeps
  its deepest: the history rule), summed as the expected plates not done within 4 passes; and the
  expected over-bent plates over those passes (``e`` each pass rolled); the mean passes a plate,
  as many as it needs.

Real advice has more spread than this (the plate's yield, the old peak, the machine's give), so its
counts are higher: a case this bound already fails, no estimate of the scatter mends.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy import optimize, stats

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.forming.advice import curvature_band, target_curvature
from pipeline.forming.campaign import SimPlate, stress_plates
from pipeline.forming.records import Machine
from pipeline.forming.rolling import PassSetup

MACHINE = Machine("R3-01", 1400.0, 420.0, 500.0)
COMPLIANCE_MM_PER_MN = 2.0


def displacement_band(plate: SimPlate) -> float:
    """The plate's tolerance band in top-roll displacement at its target, mm (its hidden factor)."""
    setup = PassSetup.of([MACHINE], [plate.record])
    target = plate.record.target

    def final(d: float) -> float:
        loaded = setup.loaded_curvature(np.array([d]), plate.yield_factor, COMPLIANCE_MM_PER_MN)
        return float(setup.unloaded_curvature(loaded, plate.yield_factor)[0])

    kt = target_curvature(target)
    d_t = optimize.brentq(lambda d: final(d) - kt, 1.0, 300.0, xtol=1e-6)
    slope = (final(d_t + 0.01) - final(d_t - 0.01)) / 0.02
    return float(curvature_band(target) / slope)


def usual_risk(b_d: np.ndarray, s: float) -> tuple[np.ndarray, np.ndarray]:
    """One pass aimed as the advice aims, the scatter known: its risk past the verdict's edge, and
    the probability that it ends short of the verdict's band."""
    median = np.minimum(0.0, 0.8 * b_d - s * stats.norm.isf(0.005))
    over = stats.norm.sf((0.95 * b_d - median) / s)
    return np.asarray(over), np.asarray(stats.norm.cdf((-0.95 * b_d - median) / s))


def three_passes(b_d: np.ndarray, s: float, risk: float) -> tuple[np.ndarray, ...]:
    """Passes after the probe, each at a risk ``risk`` past the verdict's edge (a pass is rolled
    only while the plate is short; a short pass leaves the plate at its deepest): the probability
    that the plate is still short after three, its over-bending risk over those three, and its
    expected passes, the probe's included, when it may take as many as it needs."""
    median = np.minimum(0.0, 0.95 * b_d - s * stats.norm.isf(risk))
    short = stats.norm.cdf((-0.95 * b_d - median) / s)
    over = stats.norm.sf((0.95 * b_d - median) / s)
    return (
        np.asarray(short**3),
        np.asarray(over * (1.0 + short + short**2)),
        np.asarray(1.0 + 1.0 / (1.0 - short)),
    )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(12)))
    ap.add_argument("--scatters", type=float, nargs="+", default=[0.1, 0.2])
    ap.add_argument("--risks", type=float, nargs="+", default=[0.0002, 0.001])
    args = ap.parse_args()
    plates = [p for seed in args.seeds for p in stress_plates("mixed", 20, seed)]
    b_d = np.array([displacement_band(p) for p in plates])
    q = np.quantile(b_d, [0.0, 0.05, 0.5, 0.95])
    print(
        f"{len(plates)} plates; displacement band b_d (mm): min {q[0]:.3f}, 5 % {q[1]:.3f}, "
        f"median {q[2]:.3f}, 95 % {q[3]:.3f}\n"
    )
    print(
        "| scatter mm | plates with b_d < 2 s | the aim as it is: expected over-bent (one pass), "
        "mean passes "
        + "".join(
            f"| risk {r:g}: expected not done in 4, over-bent (3 passes), mean passes "
            for r in args.risks
        )
        + "|"
    )
    print("|---" * (3 + len(args.risks)) + "|")
    for s in args.scatters:
        over, short = usual_risk(b_d, s)
        cells = [f"{over.sum():.2f}, {np.mean(1.0 + 1.0 / (1.0 - short)):.2f}"]
        for r in args.risks:
            left, risk, passes = three_passes(b_d, s, r)
            cells.append(f"{left.sum():.1f}, {risk.sum():.2f}, {passes.mean():.2f}")
        print(f"| {s:g} | {int((b_d < 2 * s).sum())} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
