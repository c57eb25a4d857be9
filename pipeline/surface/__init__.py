"""The surface: from a capture's images to a metric surface in the left camera's frame.

Modules, one job each:

- :mod:`~pipeline.surface.normals`: photometric normals and albedo (Woodham, robust);
- :mod:`~pipeline.surface.stereo`: the stereo pair's metric depth;
- :mod:`~pipeline.surface.integration`: normals integrated to depth (least squares on the grid);
- :mod:`~pipeline.surface.fusion`: the stereo correction of the photometric shape, chosen by the
  evidence;
- :mod:`~pipeline.surface.reconstruct`: the chain of the above for one view,
  :class:`~pipeline.surface.reconstruct.Surface`.
"""

import lazy_loader

# The names of __init__.pyi, each imported from its module when first used: a wing's modules import
# each other's, and eager imports here would run in circles.
__getattr__, __dir__, __all__ = lazy_loader.attach_stub(__name__, __file__)
