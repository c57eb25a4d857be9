"""plate-inspect's measurement pipeline (pure numerics; never imports ``app`` or ``web``).

Importing it changes nothing process-wide: entry points call
:func:`pipeline.parallel.configure_process` (see :mod:`pipeline.parallel`).
"""
