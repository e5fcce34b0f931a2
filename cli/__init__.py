"""The ``dualphys`` command: the pipeline's sub-commands (synth, sfm, run, render, ablate, demo, ...), ``serve`` and
the remote client's. It sits above both ``pipeline`` and ``service``, so neither imports the other's command line.

- :mod:`.main`               the parser, ``main(argv)`` and the dispatch (torch-free: the client install runs it)
- :mod:`.job_flags`          ``dualphys run``'s job flags, built from ``pipeline.job.options.JobOptions``
- :mod:`.pipeline_commands`  the pipeline's sub-commands (they import torch; loaded when one of them runs)
"""
