"""Passes per plate of simulated roll-bending campaigns, with the advice learning from the history and without.

Run from the project root:  .venv/bin/python benchmarks/bench_forming.py [--plates 20] [--seeds 0 1 2]
                            [--compliance 2.0] [--gain 1.0] [--scatter 0.1] [--yield-scatter 0]
                            [--hardening 1.0] [--batch] [--over-probability 0.005]
       .venv/bin/python benchmarks/bench_forming.py --stress --seeds 0 1 ... 11   (issue 27's cases)
                            [--cases model batch] [--modes learning] [--diagnose]

Each seed draws a batch (``pipeline.forming.campaign.random_batch``: radii 3-15 m, thickness 10-30 mm,
AH36/DH36, hidden yield 1.05-1.35 x nominal) and rolls it plate after plate on issue 14's machine against
the hidden physics (compliance, displacement gain, displacement scatter per pass, 0.05 % radius noise). "learning": the
advice sees the finished plates; "alone": each plate from the nominal model and its own passes only.
``--batch``: each seed one grade and thickness with close yields, as plates of one heat. Prints the
passes of every plate of the first seed, a summary per seed and mode, and the totals over the seeds.
``--stress --diagnose``: after each case's row, every plate over-bent, past 4 passes or not done, pass
by pass (the advice's prediction against the hidden truth), and how often the corrections' outcomes
fell beyond their predicted 97.5 % quantile, early (the first 8 plates of a campaign) and late.
"""

from __future__ import annotations

import argparse
import collections
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.forming.advice import AimSettings, aim, curvature_band, target_curvature
from pipeline.forming.campaign import (
    GRADES,
    STRESS,
    TruePhysics,
    random_batch,
    run_campaign,
    stress_plates,
    summary,
)
from pipeline.forming.learning import Priors, fit
from pipeline.forming.records import Machine, PlateRecord

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
    ap.add_argument(
        "--diagnose",
        action="store_true",
        help="with --stress: the plates over-bent, past 4 passes or not done, pass by pass, and the "
        "corrections' calibration early and late in the campaigns",
    )
    ap.add_argument(
        "--scatter-share-dof",
        action="store_true",
        help="the parameters' share of a prediction that the scatter drives takes the scatter's "
        "degrees of freedom (Priors.scatter_share_dof, a trial, off by default)",
    )
    ap.add_argument(
        "--scatter-confidence",
        type=float,
        default=None,
        help="keep the risk past the verdict's edge also with the scatter at this upper credible "
        "bound of its posterior (AimSettings.scatter_confidence; default: off)",
    )
    ap.add_argument(
        "--adaptive-split",
        action="store_true",
        help="keep the over-bending risk per plate, split over the passes it is expected to need "
        "(AimSettings.adaptive_split; default: per pass)",
    )
    ap.add_argument(
        "--verdict-probability",
        type=float,
        default=None,
        help="the risk each bending pass may take past the verdict's edge, besides the aim's "
        "(AimSettings.verdict_probability; default: off)",
    )
    ap.add_argument(
        "--scatter-two-pass",
        action="store_true",
        help="a first correction whose scatter fills the band approaches in two passes "
        "(AimSettings.scatter_two_pass; default: off)",
    )
    ap.add_argument(
        "--known-scatter",
        action="store_true",
        help="with --stress: the advice knows each case's true pass scatter (its prior at the "
        "truth, worth a million rows): what no estimate from the campaign can do better than",
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
                settings=_settings(args),
                priors=Priors(scatter_share_dof=args.scatter_share_dof),
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


def _settings(args) -> AimSettings:
    return AimSettings(
        over_probability=args.over_probability,
        scatter_confidence=args.scatter_confidence,
        adaptive_split=args.adaptive_split,
        verdict_probability=args.verdict_probability,
        scatter_two_pass=args.scatter_two_pass,
    )


def _priors(args, physics: TruePhysics) -> Priors:
    """The advice's priors: the defaults, or (``--known-scatter``) the pass scatter known."""
    if not args.known_scatter:
        return Priors(scatter_share_dof=args.scatter_share_dof)
    return Priors(
        scatter_mm=physics.displacement_scatter_mm,
        scatter_weight=1e6,
        scatter_share_dof=args.scatter_share_dof,
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
                        settings=_settings(args),
                        priors=_priors(args, physics),
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
            if args.diagnose:
                diagnose(
                    name, mode, dict(zip(args.seeds, outs)), physics, learning=mode == "learning"
                )


def _with_true_scatter(outcome, j: int, history: list, physics: TruePhysics) -> str:
    """The pass ``j`` that over-bent a plate, predicted and aimed by the same fit with the pass
    scatter known at its true value."""
    tg = outcome.record.target
    before = PlateRecord(outcome.plate_id, tg, outcome.record.passes[:j])
    priors = Priors(scatter_mm=physics.displacement_scatter_mm, scatter_weight=1e6)
    fitted = fit(
        [before, *history[-priors.max_plates :]],
        {MACHINE.machine_id: MACHINE},
        priors,
        also_machines=[MACHINE.machine_id],
    )
    setting = outcome.record.passes[j].top_roll_displacement_mm
    pred = fitted.predict(before, MACHINE.machine_id, setting)
    z = (outcome.true_curvatures[j] - pred.mean) / pred.sd
    aimed = aim(fitted, before, MACHINE)
    moved = aimed["displacement_mm"] - setting
    return (
        f"with the true scatter ({physics.displacement_scatter_mm:g} mm) known: predicted "
        f"{_bands(tg, pred.mean):+.2f} +- {1.96 * pred.sd / curvature_band(tg):.2f} (95 %), the truth "
        f"{z:+.2f} sd out; the aim {aimed['displacement_mm']:.2f} mm ({moved:+.2f} mm), median "
        f"{_bands(tg, aimed['prediction'].median):+.2f}"
    )


def _bands(target, curvature: float) -> float:
    """A mid-surface curvature as bands from the target's (+: tighter)."""
    return (curvature - target_curvature(target)) / curvature_band(target)


def _curvature(target, radius_mm) -> float:
    return 0.0 if radius_mm is None else 1.0 / target.mid_radius_mm(radius_mm)


def diagnose(name: str, mode: str, runs: dict, physics: TruePhysics, *, learning: bool) -> None:
    """Every plate over-bent, past 4 passes or not done, pass by pass: its setting, the hidden true
    curvature, the advice's median and the half-width of its 95 % range (bands from the target), the
    truth's distance from the median in those half-widths (``r``: beyond 1 is beyond the 97.5 %
    quantile), the fitted scatter; for the pass that over-bent a plate, the aim of the same fit had
    it known the true scatter (its prior at the truth, worth a million rows); then how often the
    corrections' ``r`` passed 1, by campaign position."""
    beyond: dict[str, list[float]] = {"early": [], "late": []}
    for seed, outs in runs.items():
        for i, o in enumerate(outs):
            tg = o.record.target
            flagged = o.over_bent or o.passes > 4 or o.final != "done"
            if flagged:
                print(
                    f"    {name}, {mode}, seed {seed}, plate {i + 1} ({o.plate_id}, "
                    f"{tg.material.thickness_mm:g} mm to {tg.radius_mm:.0f} mm): {o.final}"
                    f"{', over-bent' if o.over_bent else ''}, {o.passes} passes"
                )
            for j, (q, k) in enumerate(zip(o.record.passes, o.true_curvatures)):
                a = o.advice[j]
                median = _curvature(tg, a["expected_radius_mm"])
                upper = _curvature(tg, (a["expected_radius_range_mm"] or [None])[0])
                r = (k - median) / (upper - median) if upper > median else float("nan")
                if j > 0:
                    beyond["early" if i < 8 else "late"].append(r)
                if flagged:
                    scatter = a["basis"].get("parameters", {}).get("scatter_mm", float("nan"))
                    print(
                        f"      pass {j + 1}: {q.top_roll_displacement_mm:.2f} mm, true "
                        f"{_bands(tg, k):+.2f} bands, predicted {_bands(tg, median):+.2f} "
                        f"+- {(upper - median) / curvature_band(tg):.2f} (95 %), r {r:+.2f}, "
                        f"scatter {scatter:.3f} mm"
                    )
                if flagged and o.over_bent and _bands(tg, k) > physics.verdict_band:
                    history = [x.record for x in outs[:i]] if learning else []
                    print("        " + _with_true_scatter(o, j, history, physics))
    for when, rs in beyond.items():
        arr = np.array([r for r in rs if np.isfinite(r)])
        if arr.size:
            print(
                f"    {name}, {mode}: corrections {when} in their campaign (plates "
                f"{'1-8' if when == 'early' else '9-'}): {arr.size}, beyond their 97.5 % quantile "
                f"{np.mean(arr > 1):.1%} (expected 2.5 %)"
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
