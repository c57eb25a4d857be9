"""Passes per plate of simulated roll-bending campaigns, with the advice learning from the history and without.

Run from the project root:  .venv/bin/python benchmarks/bench_forming.py [--plates 20] [--seeds 0 1 2]
                            [--compliance 2.0] [--gain 1.0] [--scatter 0.1] [--yield-scatter 0]
                            [--hardening 1.0] [--batch] [--over-probability 0.005]
       .venv/bin/python benchmarks/bench_forming.py --stress --seeds 0 1 ... 11   (issue 27's cases)
                            [--cases model batch] [--modes learning]

Each seed draws a batch (``pipeline.forming.campaign.random_batch``: radii 3-15 m, thickness 10-30 mm,
AH36/DH36, hidden yield 1.05-1.35 x nominal) and rolls it plate after plate on issue 14's machine against
the hidden physics (compliance, displacement gain, displacement scatter per pass, 0.05 % radius noise). "learning": the
advice sees the finished plates; "alone": each plate from the nominal model and its own passes only.
``--batch``: each seed one grade and thickness with close yields, as plates of one heat. Prints the
passes of every plate of the first seed, a summary per seed and mode, and the totals over the seeds.
"""

from __future__ import annotations

import argparse
import collections
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.forming.advice import AimSettings
from pipeline.forming.campaign import (
    GRADES,
    STRESS,
    TruePhysics,
    random_batch,
    run_campaign,
    stress_plates,
    summary,
)
from pipeline.forming.records import Machine

MACHINE = Machine(
    "R3-01",
    bottom_roll_spacing_mm=1400.0,
    bottom_roll_diameter_mm=420.0,
    top_roll_diameter_mm=500.0,
)


def radii(outcome) -> str:
    return " ".join(
        "flat" if not np.isfinite(p.measured_radius_mm) else f"{p.measured_radius_mm:.0f}"
        for p in outcome.record.passes
    )


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--plates", type=int, default=20)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument(
        "--compliance", type=float, default=2.0, help="the machine's hidden compliance, mm/MN"
    )
    ap.add_argument(
        "--gain",
        type=float,
        default=1.0,
        help="the machine's hidden displacement gain (0.97: its geometry pushes 3 %% less than the model's)",
    )
    ap.add_argument(
        "--scatter", type=float, default=0.1, help="hidden displacement scatter of a pass, mm"
    )
    ap.add_argument(
        "--yield-scatter",
        type=float,
        default=0.0,
        help="hidden relative scatter of the yield a pass sees (not in the advice's model)",
    )
    ap.add_argument(
        "--hardening",
        type=float,
        default=1.0,
        help="hidden factor on the permanent curvature (0.98: 2 %% work hardening, not in the model)",
    )
    ap.add_argument(
        "--over-probability",
        type=float,
        default=AimSettings.over_probability,
        help="the aim's risk of ending tighter than 0.8 of the band (AimSettings)",
    )
    ap.add_argument(
        "--batch",
        action="store_true",
        help="each seed one grade and thickness (20-30 mm), yields 1.15-1.25 x nominal (one heat)",
    )
    ap.add_argument(
        "--stress",
        action="store_true",
        help="issue 27's stress cases (STRESS) over the seeds, learning and alone: one summary table",
    )
    ap.add_argument(
        "--cases",
        nargs="+",
        default=[],
        help="with --stress: only the cases whose name has one of these",
    )
    ap.add_argument(
        "--modes",
        nargs="+",
        default=["learning", "alone"],
        choices=["learning", "alone"],
        help="with --stress: the advice's modes to run (default both)",
    )
    args = ap.parse_args()
    if args.stress:
        stress(args)
        return
    physics = TruePhysics(
        compliance_mm_per_mn=args.compliance,
        displacement_gain=args.gain,
        displacement_scatter_mm=args.scatter,
        yield_scatter=args.yield_scatter,
        hardening=args.hardening,
    )
    rows, passes = [], {"learning": collections.Counter(), "alone": collections.Counter()}
    for k, seed in enumerate(args.seeds):
        plates = batch(args.plates, seed, one_heat=args.batch)
        runs = {}
        for mode in ("learning", "alone"):
            t0 = time.perf_counter()
            runs[mode] = run_campaign(
                plates,
                MACHINE,
                physics,
                np.random.default_rng(seed + 100),
                learning=mode == "learning",
                settings=AimSettings(over_probability=args.over_probability),
            )
            rows.append((seed, mode, summary(runs[mode]), time.perf_counter() - t0))
            passes[mode].update(o.passes for o in runs[mode])
        if k == 0:
            print(
                f"seed {seed}: compliance {args.compliance:g} mm/MN, gain {args.gain:g}, "
                f"scatter {args.scatter:g} mm, "
                f"yield scatter {args.yield_scatter:g}, hardening {args.hardening:g}\n"
            )
            print(
                "| plate | grade | t mm | target R mm | yield x | passes learning | passes alone "
                "| radii after each pass (learning) |"
            )
            print("|---|---|---|---|---|---|---|---|")
            for sim, a, b in zip(plates, runs["learning"], runs["alone"]):
                tg = sim.record.target
                flag = lambda o: "" if o.final == "done" else f" ({o.final})"  # noqa: E731
                print(
                    f"| {a.plate_id} | {tg.material.grade} | {tg.material.thickness_mm:g} | {tg.radius_mm:.0f} "
                    f"| {sim.yield_factor:.3f} | {a.passes}{flag(a)} | {b.passes}{flag(b)} | {radii(a)} |"
                )
            print()
    print(
        "| seed | advice | plates | done | over-bent | max passes | mean passes | mean after the first | s |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for seed, mode, s, t in rows:
        print(
            f"| {seed} | {mode} | {s['plates']} | {s['done']} | {s['over_bent']} | {s['max_passes']} "
            f"| {s['mean_passes']:.2f} | {s['mean_passes_after_first']:.2f} | {t:.0f} |"
        )
    print()
    for mode, counts in passes.items():
        after_first = [s["mean_passes_after_first"] for _, m, s, _ in rows if m == mode]
        print(
            f"{mode}: plates by passes {dict(sorted(counts.items()))}, over-bent "
            f"{sum(s['over_bent'] for _, m, s, _ in rows if m == mode)}, not done "
            f"{sum(s['plates'] - s['done'] for _, m, s, _ in rows if m == mode)}; mean after the "
            f"first plate {np.mean(after_first):.3f}, worst seed {max(after_first):.3f}"
        )


def stress(args) -> None:
    """Every stress case over the seeds, with and without learning: one table."""
    print(
        "| case | advice | plates | over-bent | expected over-bent | not done | most passes "
        "| plates past 4 passes | mean passes | mean after each batch's first | worst batch | s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, (over, kind) in STRESS.items():
        if args.cases and not any(c in name for c in args.cases):
            continue
        physics = TruePhysics(**{"compliance_mm_per_mn": args.compliance, **over})
        for mode in args.modes:
            t0, outs = time.perf_counter(), []
            for seed in args.seeds:
                outs.append(
                    run_campaign(
                        stress_plates(kind, args.plates, seed),
                        MACHINE,
                        physics,
                        np.random.default_rng(seed + 100),
                        learning=mode == "learning",
                    )
                )
            sums = [summary(o) for o in outs]
            after = np.concatenate([[p.passes for p in o[1:]] for o in outs])
            every = np.concatenate([[p.passes for p in o] for o in outs])
            print(
                f"| {name} | {mode} | {len(every)} | {sum(s['over_bent'] for s in sums)} "
                f"| {sum(expected_over(p) for o in outs for p in o):.2f} "
                f"| {sum(s['plates'] - s['done'] for s in sums)} | {int(every.max())} "
                f"| {int((every > 4).sum())} | {every.mean():.2f} | {after.mean():.2f} "
                f"| {max(s['mean_passes_after_first'] for s in sums):.2f} "
                f"| {time.perf_counter() - t0:.0f} |",
                flush=True,
            )


def expected_over(outcome) -> float:
    """The plate's expected over-bendings by the advice's own risk: the sum over its bending passes
    of the probability the advice gave of ending past the band's tight edge."""
    return sum(
        a["basis"].get("aim", {}).get("probability_over_band") or 0.0
        for a in outcome.advice
        if a["action"] == "bend" and a["top_roll_displacement_mm"] is not None
    )


def batch(n: int, seed: int, *, one_heat: bool) -> list:
    """The seed's plates: a mixed batch, or (``one_heat``) one grade and thickness of close yields."""
    rng = np.random.default_rng(seed)
    if not one_heat:
        return random_batch(n, rng)
    thickness = float(rng.choice([20.0, 25.0, 30.0]))
    grade = GRADES[int(rng.integers(len(GRADES)))]
    return random_batch(
        n, rng, thicknesses_mm=[thickness], grades=[grade], yield_factors=(1.15, 1.25)
    )


if __name__ == "__main__":
    main()
