"""Type-1 gauge studies (VDA 5 / AIAG MSA) of the simulated demo cell, a near-field LED cell and a
glossy cell (the radius's bend taken from the stereo pair).

Prints, for each cell, the table of ``plate-inspect gauge-study``: the radius and the deviation at
nine fixed points of one plate formed exactly (cylinder R 5000 mm, 3 x 3 m at 3 m), measured
``--n`` times with fresh noise, paint and light intensities; Cg, Cgk, the mean reported expanded
uncertainty against twice the observed standard deviation, and how often U covered the error.

    .venv/bin/python benchmarks/bench_gauge.py [--n 25] [--size 1224x1024]
"""

from __future__ import annotations

import argparse

from pipeline.acquisition.demo import DEMO_LED_HEIGHT_MM
from pipeline.gauge import simulated_study
from pipeline.parallel import configure_process
from pipeline.run import warm_up

#: (name, lights, LED height above the plate or None for distant lights, specular lobe's strength)
CELLS = (
    ("demo cell (8 LEDs 2.0 m above, positions given)", 8, DEMO_LED_HEIGHT_MM, 0.0),
    ("near-field LED cell (12 LEDs 2.8 m above, positions given)", 12, 2800.0, 0.0),
    ("glossy cell (12 distant lights, specular lobe 0.5)", 12, None, 0.5),
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--n", type=int, default=25, help="repeats per cell (default 25)")
    parser.add_argument("--size", default="1224x1024", help="image size WIDTHxHEIGHT")
    parser.add_argument("--seed", type=int, default=100, help="first seed of the repeats")
    args = parser.parse_args()
    configure_process()
    warm_up()
    width, height = (int(v) for v in args.size.lower().split("x"))
    for name, n_lights, height_mm, specular in CELLS:
        print(f"\n## {name}\n")
        study = simulated_study(
            n=args.n,
            width=width,
            height=height,
            n_lights=n_lights,
            near_field_mm=height_mm,
            specular=specular,
            seed=args.seed,
        )
        print(study.table())


if __name__ == "__main__":
    main()
