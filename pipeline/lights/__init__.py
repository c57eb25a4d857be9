"""The lights: how the cell's lights are modelled, fitted, refined and calibrated.

Modules, one job each:

- :mod:`~pipeline.lights.model`: :class:`~pipeline.lights.model.Lights`, distant directions or
  near-field point lights (LEDs with a beam), and the per-pixel light vectors they give;
- :mod:`~pipeline.lights.fit`: fitting point lights to intensities on a known surface;
- :mod:`~pipeline.lights.refinement`: refitting a capture's lights on the stereo geometry when the
  images' evidence for another light model is significant;
- :mod:`~pipeline.lights.calibration`: ``plate-inspect calibrate-lights``, a cell's lights measured
  from captures of a known plate;
- :mod:`~pipeline.lights.nearfield`: photometric normals under point lights, iterated with the
  surface they light.
"""

import lazy_loader

# The names of __init__.pyi, each imported from its module when first used: a wing's modules import
# each other's, and eager imports here would run in circles.
__getattr__, __dir__, __all__ = lazy_loader.attach_stub(__name__, __file__)
