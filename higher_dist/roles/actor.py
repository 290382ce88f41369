"""The actor role: B environments stepped together with one batched forward pass per step.

Needs only the learner's control address; the welcome brings the config and endpoints, and everything
else (its environments, seeds, epsilons) comes from the same `AgentBuilder` the single-process runner
uses. Weights arrive on a conflated SUB socket, polled without blocking, with the learner's frame count
that drives the epsilon schedule. Finished episodes leave in batches on a PUSH socket to the relabeler;
when that socket is full (the learner holds the replay ratio) the actor waits rather than queueing
without bound. Greedy evaluation is not done here: the learner's evaluator thread does it. Weights that
fail their checks are dropped and counted; an exception of the actor's own work (loading weights that
passed, acting, sending) stops it with one line naming the step, exit status 70 (roles/loop.py).
"""
from __future__ import annotations

import logging
import time

import numpy as np
import torch
import zmq

from higher_dist import metrics as m
from higher_dist.launch.channels import open_channel
from higher_dist.learning.acting import act
from higher_dist.learning.agent import AgentBuilder
from higher_dist.roles.client import start_role
from higher_dist.roles.loop import Every, HandlerGuard, internal, stop_on_internal_error
from higher_dist.wire import codec, sockets
from higher_dist.wire.episodes import pack_episodes
from higher_dist.wire.security import Security
from higher_dist.world.spec import SUCCESS

log = logging.getLogger("higher.actor")
SEND_EVERY_S = 0.25  # a batch leaves at least this often, full or not
WAIT_MS = 20  # longest wait for room on the episodes socket before looking at control again
FIRST_WEIGHTS_WAIT_MS = 100  # a wait for the first weights, between looks at the control channel


def run_actor(learner: str, actor_id: int | None = None, security: Security | None = None,
              threads: int | None = None) -> int:
    client, cfg, endpoints, stop = start_role(learner, "actor", actor_id, security, threads)
    idx = client.index
    agent = AgentBuilder(cfg)
    torch.manual_seed(agent.seeds.actor_torch(idx))
    ctx = zmq.Context.instance()
    weights_sub = open_channel(ctx, "weights", "connect", endpoints.weights, client.security)
    out = sockets.PendingSend(open_channel(ctx, "episodes", "connect", endpoints.episodes, client.security))
    collector = agent.collector(idx)
    policy = agent.policy(device=cfg.actor_device)
    expected = {k: v.shape for k, v in policy.net.state_dict().items()}
    rng = agent.exploration_rng(idx)
    explorer = agent.explorer(collector.n_envs)
    version, learner_frames, buffer = -1, 0, []
    frames, t0 = 0, time.time()
    send_timer, stats = Every(SEND_EVERY_S), Every(cfg.stats_every_s)
    successes, finished = 0, 0
    guard = HandlerGuard(client.rejects, log, "weights")
    try:
        while not stop and not client.poll():
            # Newest weights, if any, without waiting (an invalid frame is counted and dropped). Until the
            # first arrive (the learner publishes at start and every 2 s), wait for them instead of acting:
            # they carry the learner's frames, the exploration clock, so a resumed run does not explore at
            # the epsilon of frame 0 with an untrained network.
            msg = sockets.recv_message(weights_sub, 0 if version >= 0 else FIRST_WEIGHTS_WAIT_MS, client.rejects,
                                       "weights")
            checked = guard(msg, codec.weights_of, msg, expected) if msg is not None else None
            if checked is not None:
                new_version, arrays = checked
                learner_frames = int(msg.fields["frames"])
                if new_version != version:
                    with internal("loading weights"):
                        policy.load(arrays)
                    version = collector.weights_version = new_version
            if version < 0:
                client.heartbeat({m.FRAMES: frames, m.WEIGHTS_VERSION: version})
                continue
            if not out.flush(WAIT_MS):
                client.heartbeat({m.FRAMES: frames, m.WEIGHTS_VERSION: version})
                continue
            eps = agent.epsilons(idx, collector.n_envs, learner_frames)
            with internal("acting"):
                episodes = act(collector, policy, eps, rng, explorer)
            frames += collector.n_envs
            buffer.extend(episodes)
            finished += len(episodes)
            successes += sum(ep.outcome == SUCCESS for ep in episodes)
            now = time.time()
            if buffer and (len(buffer) >= collector.n_envs or send_timer.due(now)):
                with internal("sending episodes"):
                    fields, arrays = pack_episodes(buffer)
                    out.put(codec.encode("episodes", fields, arrays, sender=f"actor{idx}"))
                buffer = []
                send_timer.reset(now)
            client.heartbeat({m.FRAMES: frames, m.WEIGHTS_VERSION: version})
            if stats(now):
                client.stats({m.FRAMES: frames, m.FRAMES_PER_S: round(frames / max(now - t0, 1e-9), 1),
                              m.WEIGHTS_VERSION: version, m.EPSILON_MEAN: round(float(np.mean(eps)), 4),
                              m.SUCCESS_TRAIN: round(successes / max(finished, 1), 4)})
    except Exception as exc:  # noqa: BLE001 - its own code raised (roles/loop.py); a restart starts afresh
        return stop_on_internal_error(f"actor {idx}", exc, "an actor keeps no checkpoint", log)
    finally:
        weights_sub.close(linger=0)
        out.socket.close(linger=200)
        client.close()
    log.info("actor %d stopped after %d frames (%s)", idx, frames, client.stop_reason or "signal")
    return 0
