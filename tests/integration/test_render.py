"""`higher-render` on a real small-world checkpoint: a short HIGhER cluster run (learner and relabeler
checkpoints written by the roles themselves), then greedy episodes drawn as a GIF and as a PNG strip, and
a wrong pick relabelled by the run's own generator."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from hd_harness import start_cluster
from higher_dist import render
from higher_dist.learning.acting import EpisodeCollector
from higher_dist.world.spec import WRONG_PICK

pytestmark = pytest.mark.slow


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
