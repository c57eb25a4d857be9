"""Roll-bending advice for single-curvature plates on a three-roll pyramid bender (issue 14).

Modules, one job each: :mod:`.records` (inputs), :mod:`.bender` (geometry), :mod:`.springback`
(Gardiner, history rule), :mod:`.rolling` (one pass: compliance and springback), :mod:`.learning`
(parameters fitted to the history), :mod:`.reverse` (reverse passes: Masing's rule), :mod:`.advice`
(done / reverse / bend and the aim),
:mod:`.campaign` (a simulated campaign). See docs/forming.md.
"""

from .advice import Advice, AimSettings, FormingError, advise, curvature_band
from .learning import Fit, Priors, fit
from .records import FormingTarget, Machine, Material, PlateRecord, RollPass

__all__ = [
    "Advice",
    "AimSettings",
    "Fit",
    "FormingError",
    "FormingTarget",
    "Machine",
    "Material",
    "PlateRecord",
    "Priors",
    "RollPass",
    "advise",
    "curvature_band",
    "fit",
]
