"""Judging the plate: the measured surface against its target.

Modules, one job each:

- :mod:`~pipeline.judge.target_geometry`: the target's analytic or meshed geometry;
- :mod:`~pipeline.judge.registration`: the surface registered to its target;
- :mod:`~pipeline.judge.fits`: cylinder, sphere and saddle fits to measured points;
- :mod:`~pipeline.judge.curvature`: principal curvatures and the radius;
- :mod:`~pipeline.judge.deviation`: the deviation map along the target's normal;
- :mod:`~pipeline.judge.outline`: the points beyond the target's outline, left out of the judgement;
- :mod:`~pipeline.judge.area`: the area each pixel sees;
- :mod:`~pipeline.judge.uncertainty`: per-point and per-result expanded uncertainty (k = 2);
- :mod:`~pipeline.judge.verdict`: the decision rule, defects and reasons;
- :mod:`~pipeline.judge.sections`: template sections (frame lines) against the band;
- :mod:`~pipeline.judge.plate_map`: the deviation map in the target's frame for pages and reports;
- :mod:`~pipeline.judge.details`: ``details.json``, what the stages found.
"""

import lazy_loader

# The names of __init__.pyi, each imported from its module when first used: a wing's modules import
# each other's, and eager imports here would run in circles.
__getattr__, __dir__, __all__ = lazy_loader.attach_stub(__name__, __file__)
