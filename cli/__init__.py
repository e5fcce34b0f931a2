"""The ``dualphys`` command: the pipeline's sub-commands (synth, sfm, run, render, ablate, demo, ...), ``serve`` and
the remote client's. It sits above both ``pipeline`` and ``service``, so neither imports the other's command line."""
