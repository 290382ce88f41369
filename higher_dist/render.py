"""`higher-render RUN_DIR --episodes N --out FILE.gif`: watch a run's agent.

Greedy episodes of the run's latest learner checkpoint, drawn from the world's full state (not only the
agent's 7x7 view): the room with its objects (colour and shade as colour, size as size, keys square
and balls round), the agent as a triangle pointing where it faces, its view cone shaded, the mission,
the step, the outcome, and for a wrong pick the instruction the run's relabeller gives the episode (the
generator from relabeler.ckpt for HIGhER, whatever its gate says; the expert or noisy expert for HER).
`--out FILE.png` draws a strip instead: a row per episode, a few frames each.

On a BabyAI level each frame is minigrid's own picture of the room instead (render_babyai.py), with
the same text panel; a level has only its own missions, so `--goal-set` is `train` there.

The last frame of an episode shows the room before its final action (a pick moves nothing; the world
resets the room as soon as an episode ends).
"""
from __future__ import annotations

import argparse
import json
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from higher_dist.config import COLORS, SHADES, SIZES, TYPES, ConfigError, from_dict
from higher_dist.config_flags import DefaultsHelp
from higher_dist import render_babyai
from higher_dist.learning.episode import Episode
from higher_dist.learning.episode_ends import judged_stack
from higher_dist.learning.hindsight.generator_data import generator_inputs
from higher_dist.world.spec import DEFAULT_SPEC, SUCCESS, TIMEOUT, WorldSpec
from higher_dist.world.grid import DIRECTION_VECTORS, KIND_BALL, KIND_KEY, KIND_WALL, cell_attrs

BASE_RGB = {"red": (220, 40, 40), "green": (40, 170, 60), "blue": (50, 90, 230), "purple": (140, 60, 190),
            "yellow": (235, 200, 30), "grey": (130, 130, 130)}
SHADE_MIX = {"very_light": 0.6, "light": 0.3, "neutral": 0.0, "dark": -0.3, "very_dark": -0.55}  # + white, - black
SIZE_SCALE = {"tiny": 0.35, "small": 0.5, "medium": 0.65, "large": 0.8, "giant": 0.95}
PANEL_LINES = 6
LINE_H = 13
CHAR_W = 6  # Pillow's default bitmap font
STEP_MS, END_MS = 140, 1400


@dataclass
class Snapshot:
    room: np.ndarray  # (H, W, 4) view channels, wall ring included
    pos: tuple[int, int]
    direction: int
    step: int


@dataclass
class Watched:
    mission: str
    frames: list  # Snapshot (FetchAttr) or render_babyai.Picture (BabyAI), one before every action
    episode: Episode | None = None
    relabel: str = ""
    goal_set: str = "train"


def object_rgb(color: int, shade: int) -> tuple[int, int, int]:
    base = np.array(BASE_RGB[COLORS[color]], float)
    mix = SHADE_MIX[SHADES[shade]]
    rgb = base + (255 - base) * mix if mix >= 0 else base * (1 + mix)
    return tuple(int(v) for v in np.clip(rgb, 0, 255))


def draw_frame(shot: Snapshot, view_size: int, lines: list[str], cell: int = 24):
    from PIL import Image, ImageDraw

    h, w = shot.room.shape[:2]
    width = max(w * cell, 320)
    img = Image.new("RGBA", (width, h * cell + PANEL_LINES * LINE_H + 6), (255, 255, 255, 255))
    d = ImageDraw.Draw(img)
    x0 = (width - w * cell) // 2
    box = lambda r, c, m=0: (x0 + c * cell + m, r * cell + m, x0 + (c + 1) * cell - 1 - m, (r + 1) * cell - 1 - m)  # noqa: E731
    for r in range(h):
        for c in range(w):
            kind = int(shot.room[r, c, 0])
            d.rectangle(box(r, c), fill=(90, 90, 90) if kind == KIND_WALL else (236, 236, 236), outline=(210, 210, 210))
            if kind in (KIND_KEY, KIND_BALL):
                color, _, shade, size = (int(a) for a in cell_attrs(shot.room[r, c].view("<u4"))[0])
                margin = int(cell * (1 - SIZE_SCALE[SIZES[size]]) / 2)
                fill = object_rgb(color, shade)
                if kind == KIND_BALL:
                    d.ellipse(box(r, c, margin), fill=fill, outline=(0, 0, 0))
                else:
                    d.rectangle(box(r, c, margin), fill=fill, outline=(0, 0, 0))
                    cx, cy = x0 + c * cell + cell // 2, r * cell + cell // 2
                    d.rectangle((cx - 1, cy - 1, cx + 1, cy + 1), fill=(0, 0, 0))  # a keyhole: a key, not a box
    # The view cone: the view_size x view_size cells ahead, the agent at the middle of its back row.
    overlay = Image.new("RGBA", img.size, (0, 0, 0, 0))
    od = ImageDraw.Draw(overlay)
    ahead_vec = DIRECTION_VECTORS[shot.direction]
    right_vec = DIRECTION_VECTORS[(shot.direction + 1) % 4]
    for ahead in range(view_size):
        for right in range(-(view_size // 2), view_size // 2 + 1):
            r = shot.pos[0] + ahead * ahead_vec[0] + right * right_vec[0]
            c = shot.pos[1] + ahead * ahead_vec[1] + right * right_vec[1]
            if 0 <= r < h and 0 <= c < w:
                od.rectangle(box(r, c), fill=(255, 210, 0, 60))
    img = Image.alpha_composite(img, overlay)
    d = ImageDraw.Draw(img)
    r, c = shot.pos
    cx, cy, s = x0 + c * cell + cell / 2, r * cell + cell / 2, cell * 0.38
    dr, dc = ahead_vec
    side_r, side_c = right_vec
    tip = (cx + dc * s, cy + dr * s)
    back_l = (cx - dc * s + side_c * s * 0.8, cy - dr * s + side_r * s * 0.8)
    back_r = (cx - dc * s - side_c * s * 0.8, cy - dr * s - side_r * s * 0.8)
    d.polygon([tip, back_l, back_r], fill=(20, 20, 20), outline=(255, 255, 255))  # black: objects may be red
    wrapped = [part for line in lines for part in (textwrap.wrap(line, (width - 8) // CHAR_W) or [""])]
    for i, line in enumerate(wrapped[:PANEL_LINES]):
        d.text((4, h * cell + 3 + i * LINE_H), line, fill=(0, 0, 0))
    return img.convert("RGB")


def load_policy(run_dir: Path, weights: str = "online"):
    """(config, greedy policy, frames) of the run's latest learner checkpoint. weights: "online", or
    "averaged" for the moving average of the online weights the learner keeps (dqn.average_tau > 0)."""
    from higher_dist.learning.agent import AgentBuilder
    from higher_dist.rundir import RunDir

    try:
        cfg = from_dict(json.loads((run_dir / "config.json").read_text()))
    except (OSError, json.JSONDecodeError) as e:
        raise ConfigError(f"{run_dir}: no readable config.json ({e})") from None
    state = RunDir(run_dir).load_checkpoint("learner")
    if state is None:
        raise ConfigError(f"{run_dir}: no learner.ckpt to watch (has the run written a checkpoint yet?)")
    dqn = state["core"]["dqn"]
    key = "average" if weights == "averaged" else "online"
    if key not in dqn:
        raise ConfigError(f"--weights {weights}: {run_dir} kept no average of its weights (dqn.average_tau=0)")
    policy = AgentBuilder(cfg).policy()
    policy.net.load_state_dict(dqn[key])
    return cfg, policy, int(state["core"]["counters"]["frames"])


def load_relabeller(cfg, run_dir: Path):
    """(strategy, note): the run's relabel strategy, the generator loaded from relabeler.ckpt."""
    from higher_dist.learning.agent import AgentBuilder
    from higher_dist.rundir import RunDir

    strategy = AgentBuilder(cfg).relabel_strategy()
    if strategy.name != "learned":
        return strategy, ""
    state = RunDir(run_dir).load_checkpoint("relabeler")
    if state is None:
        return strategy, "no relabeler.ckpt: untrained generator"
    state.pop("pace", None)  # the relabeler service's own pacing, not the strategy's
    strategy.load_state_dict(state)
    gate = "open" if strategy.trainer.gate_open else "closed"
    return strategy, f"gate {gate}, {len(strategy.trainer.dataset)} pairs"


def relabel_text(strategy, note: str, ep: Episode, rng: np.random.Generator, spec: WorldSpec = DEFAULT_SPEC) -> str:
    """The instruction the run's relabeller gives a failed episode that achieved something (FetchAttr: a
    wrong pick; BabyAI: a time-out after an outcome of the level's kind), "" for any other episode. The
    generator describes the frame that shows the first outcome (WorldSpec.outcome_view_offset), as the
    relabeler does."""
    if ep.outcome == SUCCESS or ep.pick_step < 0:
        return ""
    if strategy.name == "none":
        return "relabel: none (this method does not relabel)"
    words = spec.language
    if strategy.name == "learned":
        tokens = strategy.trainer.generate(*generator_inputs(spec, ep, [ep.pick_step]))[0]
        text = words.decode(tokens)
        return (f"generator: \"{text}\"" + ("" if words.parse(tokens) is not None else " (unparseable: dropped)")
                + f" [{note}]")
    if strategy.name == "expert":
        return f"expert: \"{words.decode(spec.expert_tokens(np.asarray(ep.picked)[None], rng)[0])}\""
    copies = strategy.relabel([ep])
    return f"noisy expert: \"{words.decode(copies[0].mission)}\"" if copies else ""


def watch(cfg, policy, episodes: int, goal_set: str, seed: int, tile: int = 24) -> list[Watched]:
    """One greedy episode per environment of a batch of `episodes`, with the full state at every step
    (on a BabyAI level: minigrid's picture, `tile` pixels per cell)."""
    from higher_dist.learning.acting import EpisodeCollector, q_values

    if episodes < 1:
        return []  # --goal-set both with one episode: no held-out one

    collector = EpisodeCollector(cfg.world, episodes, cfg.network.frame_stack, seed, goal_set=goal_set)
    world = collector.world
    spec = WorldSpec.of(cfg.world)
    out = [Watched(spec.language.decode(collector.mission[i]), [], goal_set=goal_set) for i in range(episodes)]
    running = np.ones(episodes, bool)
    step = 0
    while running.any():
        if spec.family == "babyai":
            for i in np.flatnonzero(running):
                out[i].frames.append(render_babyai.picture(world, i, step, tile))
        else:
            pos, dirs = world.agent_pos, world.agent_dir
            for i in np.flatnonzero(running):
                out[i].frames.append(Snapshot(world.room_cells(i).copy(), tuple(int(v) for v in pos[i]),
                                              int(dirs[i]), step))
        actions = q_values(policy, collector).argmax(axis=1)
        finished = collector.step(actions)
        # A finished environment starts its next episode at once, at step 0; the collector lists the
        # finished episodes in environment order.
        for i, ep in zip(np.flatnonzero(world.steps == 0), finished):
            if running[i]:
                out[i].episode = ep
                running[i] = False
        step += 1
    return out


def outcome_text(ep: Episode, spec: WorldSpec = DEFAULT_SPEC) -> str:
    if spec.family == "babyai":
        return render_babyai.outcome_text(ep, spec.level_kind)
    if ep.outcome == SUCCESS:
        return f"SUCCESS after {ep.length} steps"
    if ep.outcome == TIMEOUT:
        return f"TIME-OUT after {ep.length} steps"
    color, kind, shade, size = (int(a) for a in ep.picked)
    return f"WRONG PICK: a {SIZES[size]} {SHADES[shade]} {COLORS[color]} {TYPES[kind]}"


def frames_of(watched: list[Watched], spec: WorldSpec, cell: int, label: str, first: int = 0, total: int = 0):
    """[(image, duration_ms)] of every episode in turn (numbered from `first` of `total`)."""
    out = []
    for k, w in enumerate(watched, start=first):
        for j, shot in enumerate(w.frames):
            last = j == len(w.frames) - 1
            lines = panel_lines(w, shot.step, last, spec, label, k, total or len(watched))
            image = (render_babyai.draw_picture(shot, lines) if spec.family == "babyai"
                     else draw_frame(shot, spec.view_size, lines, cell))
            out.append((image, END_MS if last else STEP_MS))
    return out


def panel_lines(w: Watched, step: int, last: bool, spec: WorldSpec, label: str, k: int, total: int) -> list[str]:
    """The text under a frame: run, episode, step, mission; on the last frame the outcome and the relabel."""
    goals = ("level mission" if spec.family == "babyai"
             else "held-out goal" if w.goal_set == "heldout" else "training goal")
    return [f"{label} | episode {k + 1}/{total} ({goals}) | step {step}", f"mission: {w.mission}",
            outcome_text(w.episode, spec) if last and w.episode is not None else "", w.relabel if last else ""]


def save_gif(frames, path: Path) -> None:
    images = [img.convert("P", palette=1, colors=64) for img, _ in frames]  # 1 = adaptive palette
    images[0].save(path, save_all=True, append_images=images[1:], duration=[d for _, d in frames], loop=0,
                   optimize=True)


def save_strip(watched: list[Watched], spec: WorldSpec, cell: int, label: str, path: Path, per_row: int = 6) -> None:
    from PIL import Image

    rows = []
    for k, w in enumerate(watched):
        picks = sorted(set(np.linspace(0, len(w.frames) - 1, min(per_row, len(w.frames))).round().astype(int)))
        single = frames_of([w], spec, cell, label, first=k, total=len(watched))
        rows.append([single[i][0] for i in picks])
    width = max(sum(im.width for im in row) for row in rows)
    height = sum(row[0].height for row in rows)
    strip = Image.new("RGB", (width, height), (255, 255, 255))
    y = 0
    for row in rows:
        x = 0
        for im in row:
            strip.paste(im, (x, y))
            x += im.width
        y += row[0].height
    strip.save(path, optimize=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser("higher-render", description="Draw greedy episodes of a run's latest checkpoint.",
                                     formatter_class=DefaultsHelp)
    p.add_argument("run_dir", metavar="RUN_DIR")
    p.add_argument("--episodes", type=int, default=4)
    p.add_argument("--out", default="episodes.gif", help="FILE.gif (animation) or FILE.png (a strip of frames)")
    p.add_argument("--goal-set", choices=("train", "heldout", "both"), default="train",
                   help="goals of the episodes: training, held-out, or both (alternating)")
    p.add_argument("--seed", type=int, default=0, help="seed of the episodes' layouts")
    p.add_argument("--cell", type=int, default=24, help="pixels per grid cell")
    p.add_argument("--weights", choices=("online", "averaged"), default="online",
                   help="the learner's online weights, or their moving average (dqn.average_tau)")
    p.add_argument("--tally", type=int, default=None, metavar="N",
                   help="draw nothing: play N episodes and print how they end (success, wrong outcome, cycling, "
                        "searching; docs/getting-started.md)")
    p.add_argument("--epsilon", type=float, default=0.0,
                   help="with --tally: act epsilon-greedily with this epsilon instead of greedily")
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    if args.tally is not None or args.epsilon:
        return tally_main(args)
    out = Path(args.out)
    if not 1 <= args.episodes <= 64:
        return _die("--episodes: must be in [1, 64]")
    if not 4 <= args.cell <= 64:
        return _die(f"--cell: pixels per grid cell must be in [4, 64], got {args.cell}")
    if out.suffix.lower() not in (".gif", ".png"):
        return _die(f"--out {out}: must end in .gif or .png")
    try:
        from PIL import Image  # noqa: F401
    except ImportError:
        return _die("Pillow is missing; pip install 'higher-dist[plot]'")
    run_dir = Path(args.run_dir)
    try:
        cfg, policy, frames, spec = _policy_for(run_dir, args)
        strategy, note = load_relabeller(cfg, run_dir)
    except ConfigError as e:
        return _die(str(e))
    if args.goal_set == "both":
        train = watch(cfg, policy, (args.episodes + 1) // 2, "train", args.seed, args.cell)
        heldout = watch(cfg, policy, args.episodes // 2, "heldout", args.seed, args.cell)
        watched = [w for pair in zip(train, heldout + [None]) for w in pair if w is not None][:args.episodes]
    else:
        watched = watch(cfg, policy, args.episodes, args.goal_set, args.seed, args.cell)
    rng = np.random.default_rng(args.seed)
    for w in watched:
        w.relabel = relabel_text(strategy, note, w.episode, rng, spec)
    label = f"{cfg.preset} @ {frames:,} frames" + (", averaged weights" if args.weights == "averaged" else "")
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.suffix.lower() == ".gif":
        save_gif(frames_of(watched, spec, args.cell, label), out)
    else:
        save_strip(watched, spec, args.cell, label, out)
    outcomes = [outcome_text(w.episode, spec).split(" ")[0] for w in watched]
    print(f"{out}: {len(watched)} episodes of {run_dir} ({label}): {', '.join(outcomes)}")
    return 0


def tally_main(args) -> int:
    """`--tally N`: the table of how N episodes end, printed; nothing drawn."""
    from higher_dist import tally

    if args.tally is None:
        return _die("--epsilon: goes with --tally N (drawn episodes are greedy)")
    if not 1 <= args.tally <= 4096:
        return _die(f"--tally: episodes to play must be in [1, 4096], got {args.tally}")
    if not 0.0 <= args.epsilon <= 1.0:
        return _die(f"--epsilon: must be in [0, 1], got {args.epsilon}")
    if args.goal_set == "both":
        return _die("--goal-set both: --tally scores one goal set at a time (train or heldout)")
    run_dir = Path(args.run_dir)
    try:
        cfg, policy, frames, spec = _policy_for(run_dir, args)
    except ConfigError as e:
        return _die(str(e))
    episodes = tally.play(cfg, policy, args.tally, frames, args.goal_set, args.epsilon)
    table = tally.Tally.of(spec, episodes, judged_stack(cfg.network.frame_stack, cfg.network.core))
    acting = f"epsilon {args.epsilon:g}" if args.epsilon else "greedy"
    goals = "the level's missions" if spec.family == "babyai" else f"{args.goal_set} goals"
    print(f"{run_dir}: {cfg.preset} on {cfg.world.name} @ {frames:,} frames, {args.weights} weights, {acting}, "
          f"{args.tally} episodes ({goals})\n")
    print(table.markdown())
    return 0


def _policy_for(run_dir: Path, args):
    """(config, policy, frames, world spec) of the run's checkpoint under `--weights`; ConfigError when
    there is none, or when `--goal-set` asks for held-out goals of a world that has none."""
    cfg, policy, frames = load_policy(run_dir, args.weights)
    spec = WorldSpec.of(cfg.world)
    if args.goal_set != "train" and not spec.has_heldout:
        raise ConfigError(f"--goal-set {args.goal_set}: {cfg.world.name} has no held-out goals (a BabyAI level "
                          "has only its own missions)")
    return cfg, policy, frames, spec


def _die(message: str) -> int:
    print(f"higher-render: error: {message}", file=sys.stderr)
    return 2
