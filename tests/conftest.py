"""Configuration shared by every test package: the thread policy of a process that runs inspections.

Set here, before any test runs a compiled kernel, as the CLI and the job consumer set it at start
(:func:`pipeline.parallel.configure_process`).
"""

from pipeline.parallel import configure_process

configure_process()
