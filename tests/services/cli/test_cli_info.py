"""info FILE.mcap: each channel's line says what it holds, a schemaless one included."""

from __future__ import annotations

from services.cli.info import channel_line
from services.tools.bag import ChannelInfo


def test_a_channel_line_names_the_schema_and_the_framegate_kind() -> None:
    line = channel_line(ChannelInfo("/camera/images", "framegate.Element", "frame", 50), 16)
    assert line == "  /camera/images          50 msgs  framegate.Element (frame)"


def test_a_schemaless_channel_says_so_instead_of_a_blank() -> None:
    line = channel_line(ChannelInfo("/gyro/rates/rates", "", None, 5150), 17)
    assert line.endswith("5150 msgs  no schema")
