"""What `higher-render` draws on a BabyAI level (render.py draws FetchAttr rooms and runs the command).

A frame is minigrid's own RGB picture of the env (`BatchedBabyAI.render_rgb`: the whole room, the
agent, the cells of its view highlighted) above the same text panel as a FetchAttr frame. Minigrid
draws the room from the env's live state, so the picture is taken before each action, as render.py's
FetchAttr snapshots are.

A BabyAI episode ends when the mission is achieved or at the level's step limit; achieving anything
else (picking up, reaching or opening another object, by the level's kind) does not end it. So its
outcome is a success or a time-out, and a time-out names its first achieved outcome, by the level's
verb, and counts the ones after it: hindsight may describe each of them.
"""
from __future__ import annotations

import textwrap
from dataclasses import dataclass

import numpy as np

from higher_dist.learning.episode import Episode
from higher_dist.world import babyai_language as lang
from higher_dist.world.spec import SUCCESS

# The text panel's layout: the same numbers as render.draw_frame's (this module sits below render.py
# in the import layers, so it cannot read them from there).
PANEL_LINES = 6
LINE_H = 13
CHAR_W = 6  # Pillow's default bitmap font
MIN_WIDTH = 320  # room for the panel's text under a small room


@dataclass
class Picture:
    """One step of a BabyAI episode as minigrid draws it."""

    rgb: np.ndarray  # (H, W, 3) uint8, the whole room
    step: int


def picture(world, env_index: int, step: int, tile: int) -> Picture:
    """Minigrid's picture of env `env_index` of a `BatchedBabyAI` now, `tile` pixels per cell."""
    return Picture(np.asarray(world.render_rgb(env_index, tile), dtype=np.uint8), step)


def draw_picture(shot: Picture, lines: list[str]):
    """The picture centred above the text panel, as a PIL RGB image."""
    from PIL import Image, ImageDraw

    h, w = shot.rgb.shape[:2]
    width = max(w, MIN_WIDTH)
    img = Image.new("RGB", (width, h + PANEL_LINES * LINE_H + 6), (255, 255, 255))
    img.paste(Image.fromarray(shot.rgb), ((width - w) // 2, 0))
    d = ImageDraw.Draw(img)
    wrapped = [part for line in lines for part in (textwrap.wrap(line, (width - 8) // CHAR_W) or [""])]
    for i, line in enumerate(wrapped[:PANEL_LINES]):
        d.text((4, h + 3 + i * LINE_H), line, fill=(0, 0, 0))
    return img


# What an achieved outcome did, by the level's kind (WorldSpec.level_kind).
DONE = {"pickup": "picked up", "goto": "reached", "open": "opened"}


def object_text(achieved) -> str:
    """"a red ball" (or "a red door") for an achieved object's (colour, type, location, plural) attributes."""
    color, type_ = (int(a) for a in np.asarray(achieved)[:2])
    return f"a {lang.COLORS[color]} {lang.TYPES[type_]}"


def outcome_text(ep: Episode, kind: str = "pickup") -> str:
    """"SUCCESS after 12 steps", or "TIME-OUT after 64 steps, reached a red ball first (step 9), then 2 more"
    on a level of `kind`."""
    if ep.outcome == SUCCESS:
        return f"SUCCESS after {ep.length} steps"
    text = f"TIME-OUT after {ep.length} steps"
    if ep.pick_step >= 0:
        text += f", {DONE[kind]} {object_text(ep.picked)} first (step {ep.pick_step + 1})"
        if ep.n_outcomes > 1:
            text += f", then {ep.n_outcomes - 1} more"
    return text
