"""The relabeler role: the instruction generator as a service between the actors and the learner.

Episodes come in on its PULL socket; successes feed the generator's dataset; wrong picks are relabelled
by the preset's strategy (learned generator behind its gate, expert, noisy expert or none); originals and
copies go on to the learner. The generator trains in short rounds between messages, so the stream never
waits long for it. When the learner pushes back (its socket is full) the relabeler stops reading, which
in turn pushes back on the actors. Its generator and dataset are checkpointed and resumed.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import zmq

from higher_dist.launch.channels import open_channel
from higher_dist.learning.relabel import make_relabeler
from higher_dist.roles.client import start_role
from higher_dist.rundir import RunDir
from higher_dist.wire import codec, sockets
from higher_dist.wire.security import Security
from higher_dist.wire.episodes import pack_episodes, unpack_episodes
from higher_dist.world.language import VOCAB

log = logging.getLogger("higher.relabeler")
CHECKPOINT_EVERY_S = 60.0  # at most; cfg.checkpoint_every_s when that is shorter
TRAIN_SLICE = 5  # generator steps between two looks at the sockets
WAIT_MS = 20  # longest wait on a socket before looking at control, training and stats again
IDLE_TRAIN_PER_S = 20.0  # cap on generator steps/s when there is nothing else to do (2 shared cores)


def run_relabeler(learner: str, state_dir: str | None = None, resume: bool = False, bind_host: str | None = None,
                  security: Security | None = None, threads: int | None = None, advertise: str | None = None) -> int:
    client, cfg, endpoints, stop = start_role(learner, "relabeler", 0, security, threads)
    strategy = make_relabeler(cfg, seed=cfg.seed + 1)
    trainable = strategy.name == "learned"  # only the generator has anything to train
    rd = RunDir(state_dir or Path("runs") / "relabeler")
    if resume:
        state = rd.load_checkpoint("relabeler")
        if state is not None:
            strategy.load_state_dict(state)
            log.info("resumed the relabeler's generator and dataset from %s", rd.checkpoint_path("relabeler"))
    ctx = zmq.Context.instance()
    episodes_endpoint = advertise or endpoints.episodes
    # A CURVE server of its own: the security object starts this process's authenticator on first bind.
    inbox = open_channel(ctx, "episodes", "bind", episodes_endpoint, client.security, bind_host)
    outbox = open_channel(ctx, "experience", "connect", endpoints.experience, client.security)
    client.send("register", {"role": "relabeler", "endpoint": episodes_endpoint})
    pending, received, relabelled = None, 0, 0
    last_stats = last_ckpt = last_train = time.time()
    relabels_window = (time.time(), 0)
    relabels_per_s = 0.0
    try:
        while not stop and not client.poll():
            # Wait, briefly, rather than spin: a full outbox is the learner holding its replay ratio.
            if pending is not None and outbox.poll(WAIT_MS, zmq.POLLOUT):
                try:
                    outbox.send_multipart(pending, flags=zmq.NOBLOCK, copy=False)
                    pending = None
                except zmq.Again:
                    pass
            msg = None
            if pending is None:
                msg = sockets.recv_message(inbox, WAIT_MS, client.rejects)
            if msg is not None and msg.type == "episodes":
                try:
                    episodes = unpack_episodes(msg, max_steps=cfg.world.max_steps,
                                               view_size=cfg.world.view_size, vocab_size=len(VOCAB))
                except codec.WireError as e:
                    client.rejects.add(e.reason)
                    episodes = []
                if episodes:
                    received += len(episodes)
                    strategy.observe(episodes)
                    copies = strategy.relabel(episodes)
                    relabelled += len(copies)
                    fields, arrays = pack_episodes(episodes + copies)
                    pending = codec.encode("episodes", fields, arrays, sender="relabeler")
            elif msg is not None:
                client.rejects.add("unexpected_type")
            now = time.time()
            # Train between messages; when idle, at a capped rate so actors and learner keep the CPU.
            if trainable and (msg is not None or now - last_train > TRAIN_SLICE / IDLE_TRAIN_PER_S):
                strategy.train(TRAIN_SLICE)
                last_train = now
            client.heartbeat({"episodes": received, "relabelled": relabelled})
            if now - last_stats > cfg.stats_every_s:
                t_w, n_w = relabels_window
                relabels_per_s = (relabelled - n_w) / max(now - t_w, 1e-9)
                relabels_window = (now, relabelled)
                m = strategy.metrics()
                client.send("register", {"role": "relabeler", "endpoint": episodes_endpoint})
                client.stats({"episodes": received, "relabelled": relabelled,
                              "relabels_per_s": round(relabels_per_s, 2), **_flat(m)})
                last_stats = now
            if now - last_ckpt > min(CHECKPOINT_EVERY_S, cfg.checkpoint_every_s):
                rd.save_checkpoint("relabeler", strategy.state_dict())
                last_ckpt = now
    finally:
        rd.save_checkpoint("relabeler", strategy.state_dict())
        inbox.close(linger=0)
        outbox.close(linger=500)
        client.close()
    log.info("relabeler stopped: %d episodes in, %d relabelled", received, relabelled)
    return 0


def _flat(metrics: dict) -> dict:
    out = {}
    for k, v in metrics.items():
        if isinstance(v, (int, float, str, bool)) or v is None:
            out[k] = v
    return out
