"""MiniGrid from pixels: MiniGrid's agent view rendered as RGB, registered as gymnasium ids
(``rlpipe/MiniGrid-Empty-5x5-Pixels-v0``) that build once the ``minigrid`` extra is installed."""

from __future__ import annotations

from typing import Any

import gymnasium as gym

from rlpipe.errors import RlpipeError

__all__ = ["PIXEL_IDS", "minigrid_pixels"]

MINIGRID_INSTALL = 'pip install "rlpipe[minigrid]"'
# rlpipe's id -> MiniGrid's
PIXEL_IDS = {"rlpipe/MiniGrid-Empty-5x5-Pixels-v0": "MiniGrid-Empty-5x5-v0"}


def minigrid_pixels(env_id: str, tile_size: int = 4, **kwargs: Any) -> gym.Env:
    """MiniGrid's ``env_id`` observed as the RGB image of its agent's 7x7-cell partial view,
    ``tile_size`` pixels a cell (4: 28x28x3 uint8), without the direction and mission
    (MiniGrid's ``RGBImgPartialObsWrapper`` then ``ImgObsWrapper``)."""
    try:
        import minigrid  # noqa: F401  (registers MiniGrid's ids)
        from minigrid.wrappers import ImgObsWrapper, RGBImgPartialObsWrapper
    except ImportError as err:
        raise RlpipeError(f"{env_id} needs MiniGrid: {MINIGRID_INSTALL}") from err
    return ImgObsWrapper(RGBImgPartialObsWrapper(gym.make(env_id, **kwargs), tile_size))


for _id, _minigrid_id in PIXEL_IDS.items():
    gym.register(_id, entry_point=minigrid_pixels, kwargs={"env_id": _minigrid_id})
