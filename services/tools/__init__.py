"""A user's tools around a running pipeline: ``bag`` (record, play, info of MCAP files),
``view`` (the Foxglove bridge) and ``demo``. The benchmarks and the paper's experiment live
in ``services.evidence``."""
