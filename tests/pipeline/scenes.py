"""Surroundings of simulated plates that several tests render."""

from __future__ import annotations

from pipeline.simulate import Floor, rail_supports


def dark_floor_with_rails() -> Floor:
    """Three rails 300 mm under a 3 m plate over a dark, untextured floor: only the rails' bright tops
    are lit, and they join the plate's brightness mask (``bench_surroundings.py``'s *dark floor, rails*)."""
    return Floor(
        gap_mm=300.0, albedo=0.03, texture=0.0, supports=rail_supports((3000.0, 3000.0), 300.0, 3)
    )
