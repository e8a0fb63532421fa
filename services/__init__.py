"""framegate's services: the processes of the paper's pipeline, and everything around them.

What lives where (imports only ever point down this list)::

    services/
    ├── cli/       the `framegate` command: one thin module per command
    ├── evidence/  what backs the claims: bench (vs raw Zenoh), experiment (the paper's
    │              Table 1), soak, faultbench; nothing of the product imports it
    ├── tools/     a user's programs around a pipeline: demo, bag (MCAP record/play),
    │              view (live Foxglove)
    ├── launch/    deploy files, the pipeline definition, the process supervisor
    ├── nodes/     the four service processes (camera, gyro, mediator, detector), their
    │              one contract and registry, camera/gyro sources
    └── lib/       domain libraries with no process of their own: blur quality, the
                   mediator's decisions, markers, camera model, message kinds, clock
                   offsets, the simulated world, b0 calibration

    middleware/    (beside services/) buffers, queries, notifications, flow control

Import direction: ``cli → evidence → tools → launch → nodes → lib → middleware``. A package
may import anything below it and nothing above it; ``middleware`` imports nothing of
``services``.
``tests/test_architecture.py`` keeps it so.
"""
