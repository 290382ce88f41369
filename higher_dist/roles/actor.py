"""The actor role: B environments stepped together with one batched forward pass per step.

Needs only the learner's control address; the welcome brings the config and endpoints. Weights arrive
on a conflated SUB socket and are polled without blocking; finished episodes leave in batches on a
PUSH socket to the relabeler. When that socket is full (the learner holds the replay ratio) the actor
waits rather than queueing without bound. Actor 0 also runs the periodic greedy evaluation.
"""
from __future__ import annotations

import logging
import time

import numpy as np
import torch
import zmq

from higher_dist.launch.channels import open_channel
from higher_dist.learning.acting import EpisodeCollector, TorchQFunction, act, evaluate_goal_sets
from higher_dist.learning.episode import SUCCESS
from higher_dist.learning.exploration import actor_epsilons
from higher_dist.roles.client import start_role
from higher_dist.wire import codec, sockets
from higher_dist.wire.episodes import pack_episodes
from higher_dist.wire.security import Security

log = logging.getLogger("higher.actor")
SEND_EVERY_S = 0.25  # a batch leaves at least this often, full or not
WAIT_MS = 20  # longest wait for room on the episodes socket before looking at control again


def run_actor(learner: str, actor_id: int | None = None, security: Security | None = None,
              threads: int | None = None) -> int:
    client, cfg, endpoints, stop = start_role(learner, "actor", actor_id, security, threads)
    idx = client.index
    torch.manual_seed(cfg.seed + idx)
    ctx = zmq.Context.instance()
    weights_sub = open_channel(ctx, "weights", "connect", endpoints.weights, client.security)
    out = open_channel(ctx, "episodes", "connect", endpoints.episodes, client.security)
    collector = EpisodeCollector(cfg.world, cfg.envs_per_actor, cfg.network.frame_stack,
                                 seed=cfg.seed * 1000 + 17 * (idx + 1), actor_id=idx)
    policy = TorchQFunction(cfg.network)
    expected = {k: v.shape for k, v in policy.net.state_dict().items()}
    rng = np.random.default_rng(cfg.seed * 7919 + idx)
    version, buffer, pending = -1, [], None
    frames, last_send, last_stats, t0 = 0, time.time(), time.time(), time.time()
    successes, finished = 0, 0
    next_eval = cfg.eval.every_frames
    eval_result: dict[str, float] = {}
    try:
        while not stop and not client.poll():
            # Newest weights, if any, without waiting (an invalid frame is counted and dropped).
            weights = sockets.recv_weights(weights_sub, expected, 0, client.rejects)
            if weights is not None and weights[0] != version:
                policy.load(weights[1])
                version = collector.weights_version = weights[0]
            if pending is not None:
                # A full socket is the learner holding its replay ratio: wait for room, do not spin.
                if out.poll(WAIT_MS, zmq.POLLOUT):
                    try:
                        out.send_multipart(pending, flags=zmq.NOBLOCK, copy=False)
                        pending = None
                    except zmq.Again:
                        pass
                if pending is not None:
                    client.heartbeat({"frames": frames, "weights_version": version})
                    continue
            # The global frame count drives linear epsilon decay; each actor sees about 1/N of it.
            eps = actor_epsilons(cfg.exploration, idx, cfg.actors, collector.n_envs, frames * cfg.actors)
            episodes = act(collector, policy, eps, rng)
            frames += collector.n_envs
            buffer.extend(episodes)
            finished += len(episodes)
            successes += sum(ep.outcome == SUCCESS for ep in episodes)
            now = time.time()
            if buffer and (len(buffer) >= collector.n_envs or now - last_send > SEND_EVERY_S):
                fields, arrays = pack_episodes(buffer)
                pending = codec.encode("episodes", fields, arrays, sender=f"actor{idx}")
                buffer, last_send = [], now
            if idx == 0 and frames * cfg.actors >= next_eval and version >= 0:
                next_eval += cfg.eval.every_frames
                eval_result = evaluate_goal_sets(policy, cfg, seed=cfg.seed + 10_000 + frames)
            client.heartbeat({"frames": frames, "weights_version": version})
            if now - last_stats > cfg.stats_every_s:
                client.stats({"frames": frames, "frames_per_s": round(frames / max(now - t0, 1e-9), 1),
                              "weights_version": version, "epsilon_mean": round(float(np.mean(eps)), 4),
                              "success_rate": round(successes / max(finished, 1), 4), **eval_result})
                last_stats = now
    finally:
        weights_sub.close(linger=0)
        out.close(linger=200)
        client.close()
    log.info("actor %d stopped after %d frames (%s)", idx, frames, client.stop_reason or "signal")
    return 0
