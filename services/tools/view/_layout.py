"""The Foxglove layout for framegate, built with the SDK.

It is installed with the package (``installed_layout()``, named by ``framegate view`` at
start) and kept in the repository as ``deploy/foxglove-layout.json``; a test checks that both
files hold what ``foxglove_layout()`` builds.

The camera image with the mediator's verdicts and the detector's markers drawn on it; q,
load and accepted over time; the blur estimate and the gyro rate over time; the verdicts as
raw messages. It names only topics that both ``framegate view`` and ``framegate record``
produce, so it works live and on a recording.
"""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path

import foxglove.layouts as fl

from services.tools.bag import annotations_topic, image_topic, rates_topic, verdict_topic

CAMERA = ("camera", "images")
DECISIONS = ("mediator", "decisions")
DETECTIONS = ("detector", "detections")
GYRO = ("gyro", "rates")


def _plot(title: str, series: list[tuple[str, str]]) -> fl.PlotPanel:
    return fl.PlotPanel(
        title=title,
        config=fl.PlotConfig(
            paths=[fl.PlotSeries(value=path, label=label) for label, path in series],
            show_legend=True,
        ),
    )


LAYOUT_FILE = "foxglove-layout.json"


def installed_layout() -> Path:
    """Where the installed package keeps the layout (to import into Foxglove)."""
    return Path(str(resources.files(__package__ or "services.tools.view") / LAYOUT_FILE))


def foxglove_layout() -> str:
    """The layout as pretty JSON (what the repository's file holds)."""
    verdict = verdict_topic(*DECISIONS)
    image = fl.ImagePanel(
        title="camera: verdicts and markers",
        config=fl.ImageConfig(
            image_mode=fl.ImageModeConfig(
                image_topic=image_topic(*CAMERA),
                annotations={
                    annotations_topic(*DECISIONS): fl.ImageAnnotationSettings(visible=True),
                    annotations_topic(*DETECTIONS): fl.ImageAnnotationSettings(visible=True),
                },
            )
        ),
    )
    quality = _plot(
        "mediator: q against load",
        [("q", f"{verdict}.q"), ("load", f"{verdict}.load"), ("accepted", f"{verdict}.accepted")],
    )
    motion = _plot(
        "blur estimate (px) and gyro rate (rad/s)",
        [("blur_px", f"{verdict}.blur_px"), ("gyro |w|", f"{rates_topic(*GYRO)}.norm_rad_s")],
    )
    raw = fl.RawMessagesPanel(title="verdicts", config=fl.RawMessagesConfig(topic_path=verdict))
    layout = fl.Layout(
        content=fl.SplitContainer(
            direction="row",
            items=[
                fl.SplitItem(proportion=3, content=image),
                fl.SplitItem(
                    proportion=2,
                    content=fl.SplitContainer(
                        direction="column",
                        items=[
                            fl.SplitItem(content=quality),
                            fl.SplitItem(content=motion),
                            fl.SplitItem(content=raw),
                        ],
                    ),
                ),
            ],
        )
    )
    return json.dumps(json.loads(layout.to_json()), indent=2) + "\n"


if __name__ == "__main__":  # python -m services.tools.view._layout > deploy/foxglove-layout.json
    print(foxglove_layout(), end="")
