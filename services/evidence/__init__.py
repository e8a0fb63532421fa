"""The evidence behind framegate's claims, kept out of the way of the product.

``bench`` (framegate against raw Zenoh, side by side in one run), ``experiment`` (the
paper's marker experiment, reproduced end to end), ``soak`` (the pipeline at full speed
for a long time) and ``faultbench`` (services killed in turn). Nothing in ``middleware``,
``services/nodes``, ``services/lib`` or ``services/tools`` imports from here.
"""
