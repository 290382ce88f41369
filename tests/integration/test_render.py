"""`higher-render` on a real small-world checkpoint: a short HIGhER cluster run (learner and relabeler
checkpoints written by the roles themselves), then greedy episodes drawn as a GIF and as a PNG strip, and
a wrong pick relabelled by the run's own generator."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch

from hd_harness import start_cluster
from higher_dist import render
from higher_dist.learning.acting import EpisodeCollector
from higher_dist.world.spec import WRONG_PICK

pytestmark = pytest.mark.slow
torch.set_num_threads(1)  # the default spins every core, and these tests share the machine


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    base = tmp_path_factory.mktemp("render")
    run = base / "run"
    watch, launcher, _ = start_cluster(run, base, frames=1500, actors=1)
    try:
        rc = launcher.wait(150)
        assert rc == 0, watch.diagnostics()
    finally:
        watch.cleanup()
    assert (run / "learner.ckpt").exists() and (run / "relabeler.ckpt").exists()
    return run


def test_gif_and_strip_of_greedy_episodes(run_dir, tmp_path):
    from PIL import Image

    gif, strip = tmp_path / "episodes.gif", tmp_path / "episodes.png"
    for out in (gif, strip):
        proc = subprocess.run([sys.executable, "-c", "import sys; from higher_dist.cli import render_main as m; "
                               "sys.exit(m())", str(run_dir), "--episodes", "3", "--goal-set", "both", "--out", str(out)],
                              capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0, proc.stdout + proc.stderr
        assert "3 episodes" in proc.stdout
    # One episode of "both" is a training-goal one (there is no held-out one to alternate with).
    one = tmp_path / "one.png"
    proc = subprocess.run([sys.executable, "-c", "import sys; from higher_dist.cli import render_main as m; "
                           "sys.exit(m())", str(run_dir), "--episodes", "1", "--goal-set", "both", "--out", str(one)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and "1 episodes" in proc.stdout and one.is_file(), proc.stdout + proc.stderr
    with Image.open(gif) as im:
        assert im.format == "GIF" and im.n_frames >= 3
        assert gif.stat().st_size < 300_000
    with Image.open(strip) as im:
        assert im.format == "PNG" and im.height > 3 * 7 * 20  # a row per episode, each a room of 5x5 cells or more


def test_each_step_shows_the_whole_room_and_the_agent(run_dir):
    cfg, policy, frames = render.load_policy(run_dir)
    assert frames > 0
    watched = render.watch(cfg, policy, episodes=4, goal_set="train", seed=3)
    room = cfg.world.room_size + 2
    for w in watched:
        assert w.episode is not None
        assert len(w.frames) == w.episode.length  # one snapshot before every action
        first = w.frames[0]
        assert first.room.shape == (room, room, 4)
        assert (first.room[..., 0] >= 3).sum() == cfg.world.n_objects  # every object, in or out of view
        assert 1 <= first.pos[0] <= cfg.world.room_size and 1 <= first.pos[1] <= cfg.world.room_size
    image = render.draw_frame(watched[0].frames[0], cfg.world.view_size, ["a", "b"], cell=20)
    r, c = watched[0].frames[0].pos
    x0 = (image.width - room * 20) // 2
    centre = np.asarray(image)[r * 20 + 10, x0 + c * 20 + 10]
    assert centre.max() < 60  # the agent is drawn (black) where the world says it is


def test_a_wrong_pick_gets_the_generators_instruction(run_dir):
    cfg, _, _ = render.load_policy(run_dir)
    strategy, note = render.load_relabeller(cfg, run_dir)
    assert strategy.name == "learned" and "pairs" in note
    collector = EpisodeCollector(cfg.world, 16, cfg.network.frame_stack, seed=5)
    rng = np.random.default_rng(0)
    wrong = None
    while wrong is None:
        for ep in collector.step(rng.integers(4, size=16)):
            if ep.outcome == WRONG_PICK:
                wrong = ep
    text = render.relabel_text(strategy, note, wrong, rng)
    assert text.startswith('generator: "') and note in text, text
    assert render.relabel_text(strategy, note, _with_outcome(wrong, 0), rng) == ""  # successes are not relabelled


def _with_outcome(ep, outcome):
    from dataclasses import replace

    return replace(ep, outcome=outcome)


def test_refuses_a_folder_without_a_checkpoint(tmp_path, capsys):
    assert render.main([str(tmp_path), "--out", str(tmp_path / "x.gif")]) == 2
    assert "no readable config.json" in capsys.readouterr().err
    assert render.main([str(tmp_path), "--out", str(tmp_path / "x.mp4")]) == 2
    assert "must end in .gif or .png" in capsys.readouterr().err
    assert not (tmp_path / "x.gif").exists()

    for flags, message in ((["--cell", "0"], "--cell"), (["--episodes", "0"], "--episodes")):
        assert render.main([str(tmp_path), "--out", str(tmp_path / "x.gif"), *flags]) == 2
        assert message in capsys.readouterr().err


def test_tally_counts_the_runs_greedy_episodes_as_its_evaluation_does(run_dir, capsys):
    from higher_dist.learning.acting import evaluate
    from higher_dist.learning.seeds import Seeds

    assert render.main([str(run_dir), "--tally", "48"]) == 0
    out = capsys.readouterr().out
    # A row per mission prefix (the prefix names nothing), then every mission together.
    from higher_dist.world.language import PREFIXES
    rows = {c[0]: c for c in ([x.strip() for x in line.strip("|").split("|")] for line in out.splitlines()
                              if line.startswith("| ") and not line.startswith("| missions"))}
    prefixes = [name for name in rows if name in PREFIXES]
    assert len(prefixes) >= 2 and sum(int(rows[name][1]) for name in prefixes) == 48
    cells = rows["every mission"]
    assert cells[1] == "48" and abs(sum(float(c.rstrip("%")) for c in cells[2:]) - 100) < 0.5
    # Its success share is the run's own greedy evaluation on the same goals (one episode per environment).
    cfg, policy, frames = render.load_policy(run_dir)
    rate, _ = evaluate(policy, cfg.world, cfg.network.frame_stack, "train", Seeds(cfg.seed).evaluation_env_seeds(frames, 48))
    assert cells[2] == f"{100 * rate:.1f}%"
    assert f"@ {frames:,} frames, online weights, greedy, 48 episodes (train goals)" in out
    assert render.main([str(run_dir), "--tally", "8", "--goal-set", "heldout", "--epsilon", "0.3"]) == 0
    assert "epsilon 0.3, 8 episodes (heldout goals)" in capsys.readouterr().out


def test_tally_refuses_bad_flags_by_name(run_dir, capsys):
    for flags, message in ((["--tally", "0"], "--tally"), (["--tally", "5000"], "--tally"),
                           (["--tally", "4", "--epsilon", "1.5"], "--epsilon"), (["--epsilon", "0.1"], "goes with --tally"),
                           (["--tally", "4", "--goal-set", "both"], "--goal-set both")):
        assert render.main([str(run_dir), *flags]) == 2
        assert message in capsys.readouterr().err


def test_the_averaged_weights_can_be_drawn_and_a_run_without_them_is_refused(run_dir, tmp_path, capsys):
    import shutil

    import torch

    from higher_dist.rundir import RunDir

    state = RunDir(run_dir).load_checkpoint("learner")
    dqn = state["core"]["dqn"]
    assert "average" in dqn  # the default config keeps the average
    _, online, _ = render.load_policy(run_dir)
    _, averaged, _ = render.load_policy(run_dir, "averaged")
    for name, tensor in averaged.net.state_dict().items():
        assert torch.equal(tensor, dqn["average"][name])
    assert any(not torch.equal(a, b) for a, b in zip(online.net.state_dict().values(),
                                                    averaged.net.state_dict().values()))
    out = tmp_path / "avg.png"
    assert render.main([str(run_dir), "--episodes", "1", "--weights", "averaged", "--out", str(out)]) == 0
    assert "averaged weights" in capsys.readouterr().out and out.is_file()
    # A run that kept no average (dqn.average_tau=0) is refused by name, with nothing drawn.
    plain = tmp_path / "plain"
    shutil.copytree(run_dir, plain)
    del dqn["average"]
    RunDir(plain).save_checkpoint("learner", state)
    assert render.main([str(plain), "--weights", "averaged", "--out", str(tmp_path / "none.png")]) == 2
    err = capsys.readouterr().err
    assert "--weights averaged" in err and "dqn.average_tau=0" in err
    assert not (tmp_path / "none.png").exists()


# -- a BabyAI level: minigrid's own picture of the room, the level's outcomes and language ------------
LEVEL = "BabyAI-PickupDist-v0"


@pytest.fixture(scope="module")
def babyai_run(tmp_path_factory):
    """A real HER run on a BabyAI level, learner and relabeler checkpoints written by the roles (~1 min)."""
    from hd_harness import entry
    from higher_dist.launch.topology import free_base_port

    run = tmp_path_factory.mktemp("render-babyai") / "run"
    proc = subprocess.run(entry("cluster", "--preset", "her", "--world", LEVEL, "--frames", "3000", "--actors", "1",
                                "--no-dashboard", "--run-dir", run, "--port-base", free_base_port()),
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert (run / "learner.ckpt").exists()
    return run


def test_babyai_gif_and_strip_are_minigrids_pictures(babyai_run, tmp_path, capsys):
    from PIL import Image

    from higher_dist.world.babyai import BatchedBabyAI

    gif, strip = tmp_path / "babyai.gif", tmp_path / "babyai.png"
    for out in (gif, strip):
        assert render.main([str(babyai_run), "--episodes", "2", "--cell", "16", "--out", str(out)]) == 0
        assert f"2 episodes of {babyai_run}" in capsys.readouterr().out
    level = BatchedBabyAI(LEVEL, 1)
    level.reset()
    picture = level.render_rgb(0, 16)  # the level's whole room, 16 pixels per cell
    size = (max(picture.shape[1], 320), picture.shape[0] + render.PANEL_LINES * render.LINE_H + 6)
    with Image.open(gif) as im:
        assert im.format == "GIF" and im.n_frames >= 3 and im.size == size
    with Image.open(strip) as im:
        assert im.format == "PNG" and im.height == 2 * size[1]  # a row per episode


def test_babyai_watch_takes_a_picture_before_every_action(babyai_run):
    cfg, policy, _ = render.load_policy(babyai_run)
    (watched,) = render.watch(cfg, policy, episodes=1, goal_set="train", seed=2, tile=8)
    assert len(watched.frames) == watched.episode.length
    assert [shot.step for shot in watched.frames] == list(range(watched.episode.length))
    assert watched.frames[0].rgb.ndim == 3 and watched.frames[0].rgb.shape[2] == 3
    assert watched.mission.startswith("pick up ")


def test_babyai_panel_of_a_time_out_after_a_pickup_names_the_relabel(babyai_run):
    from higher_dist.config_presets import make_config
    from higher_dist.learning.agent import AgentBuilder
    from higher_dist.learning.random_episodes import real_episodes
    from higher_dist.world import babyai_language as lang
    from higher_dist.world.spec import TIMEOUT, WorldSpec

    cfg, _, _ = render.load_policy(babyai_run)
    spec = WorldSpec.of(cfg.world)
    strategy, note = render.load_relabeller(cfg, babyai_run)
    assert strategy.name == "expert" and note == ""
    episodes = real_episodes(cfg.world, 40, seed=1)
    failed = next(ep for ep in episodes if ep.outcome == TIMEOUT and ep.pick_step >= 0)
    rng = np.random.default_rng(0)
    color, type_ = lang.COLORS[failed.picked[0]], lang.TYPES[failed.picked[1]]
    article = lang.ARTICLES[failed.picked[3]]
    text = render.relabel_text(strategy, note, failed, rng, spec)
    assert text == f'expert: "pick up {article} {color} {type_}"'
    watched = render.Watched(lang.decode(failed.mission), [], episode=failed, relabel=text)
    lines = render.panel_lines(watched, failed.length - 1, True, spec, "her", 0, 1)
    assert lines[1] == f"mission: {lang.decode(failed.mission)}"
    later = f", then {failed.n_outcomes - 1} more" if failed.n_outcomes > 1 else ""
    assert lines[2] == (f"TIME-OUT after {failed.length} steps, picked up a {color} {type_} first "
                        f"(step {failed.pick_step + 1}){later}")
    assert lines[3] == text and "level mission" in lines[0]
    assert render.panel_lines(watched, 0, False, spec, "her", 0, 1)[2:] == ["", ""]  # only the last frame tells
    # Neither a success nor a time-out that picked nothing is relabelled.
    for ep in episodes:
        if ep.outcome != TIMEOUT or ep.pick_step < 0:
            assert render.relabel_text(strategy, note, ep, rng, spec) == ""
    # HIGhER's generator describes the frame before the first pickup, in the level's language.
    learned = AgentBuilder(make_config("higher", LEVEL)).relabel_strategy()
    seen = []
    generate = learned.trainer.generate
    learned.trainer.generate = lambda views, where=None: seen.append(views.copy()) or generate(views, where)
    text = render.relabel_text(learned, "gate closed", failed, rng, spec)
    assert text.startswith('generator: "') and text.endswith("[gate closed]"), text
    np.testing.assert_array_equal(seen[0][0], failed.frames[failed.pick_step])


def test_babyai_tally_has_a_row_per_location_phrase(babyai_run, capsys):
    assert render.main([str(babyai_run), "--tally", "24"]) == 0
    out = capsys.readouterr().out
    # PickupDist's missions name no location: one row, "none", and no total row beside it.
    assert "| none | 24 |" in out and "every mission" not in out and "24 episodes (the level's missions)" in out
    assert render.main([str(babyai_run), "--tally", "4", "--goal-set", "heldout"]) == 2
    assert "no held-out goals" in capsys.readouterr().err


def test_babyai_has_no_held_out_goals_to_draw(babyai_run, tmp_path, capsys):
    for goal_set in ("heldout", "both"):
        assert render.main([str(babyai_run), "--goal-set", goal_set, "--out", str(tmp_path / "x.png")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"{LEVEL} has no held-out goals" in err[0]
    assert not (tmp_path / "x.png").exists()
