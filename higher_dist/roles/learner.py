"""The learner role: the head of the cluster.

A short loop around `LearnerCore`: answer control messages (hello -> welcome with the run's config and
endpoints), take episode batches while the samples-per-insert ratio allows (otherwise the sockets'
high-water marks push back on the relabeler and the actors), run DQN updates, publish weights, start
greedy evaluations on a background thread, write metrics and telemetry, checkpoint. Ends when the frame
budget is reached or on SIGTERM/SIGINT.

No input can end the loop: every incoming episode is checked against the run's `WorldSpec` where it is
unpacked (wire/episodes.py) and dropped, counted by reason, when it fails; an unexpected exception while
handling one message is logged with the message's type and sender, counted as `handler_error`, and the
loop goes on. Relabelled episodes are accepted only in messages whose sender is the relabeler: an actor
never relabels, so such a claim from anyone else is dropped as `relabel_origin`.
"""
from __future__ import annotations

import logging
import os
import signal
import socket
import time

import numpy as np
import torch
import zmq

from higher_dist import config as config_mod
from higher_dist import metrics as m
from higher_dist.config import Config
from higher_dist.launch.channels import check_binds, open_channel
from higher_dist.launch.topology import Endpoints
from higher_dist.learning.agent import AgentBuilder
from higher_dist.roles.client import REJECT_STAT_PREFIX, REJOIN
from higher_dist.roles.evaluator import BackgroundEvaluator
from higher_dist.roles.registry import NoSlot, RateMeter, RoleRegistry
from higher_dist.rundir import RunDir, plain_record
from higher_dist.wire import codec, sockets
from higher_dist.wire.security import Security
from higher_dist.wire.episodes import unpack_episodes
from higher_dist.wire.schema import PROTOCOL_VERSION

log = logging.getLogger("higher.learner")
TELEMETRY_EVERY_S = 0.5
WEIGHTS_REPUBLISH_S = 2.0  # late subscribers (a restarted actor) get weights within this time


class LearnerRole:
    def __init__(self, cfg: Config, endpoints: Endpoints, run_dir: str, resume: bool = False,
                 bind_host: str | None = None, security: Security | None = None):
        torch.set_num_threads(cfg.torch_threads)
        torch.manual_seed(cfg.seed)
        self.cfg, self.endpoints = cfg, endpoints
        # Without keys, every port bound beyond loopback is named at once, before anything is written:
        # refused, or warned about under --insecure.
        self.security = security or Security()
        check_binds(endpoints, bind_host, self.security, binder="learner")
        self.rd = RunDir(run_dir, tensorboard=cfg.tensorboard)
        self.agent = AgentBuilder(cfg)
        self.core = self.agent.learner_core()
        self.evaluator = BackgroundEvaluator(self.agent)
        self.registry = RoleRegistry()
        self.rejects = sockets.RejectCounter()
        self.relabeler_endpoint: str | None = None
        self.pending_hellos: list[tuple[bytes, int]] = []
        self.weights_version = 0
        self.stop_reason = ""
        self.handler_errors = 0
        self.started = time.time()
        self.updates_rate = RateMeter()
        if resume:
            self._resume()
        elif self.rd.checkpoint_path("learner").exists():
            raise ValueError(f"--run-dir {self.rd.path} already holds a run: add --resume to continue it, "
                             "or choose another --run-dir")
        self.evaluation = self.agent.evaluation_cadence(self.core.frames)
        self.rd.write_config(cfg)
        ctx = zmq.Context.instance()
        # With keys, every socket is a CURVE server and only clients on the allow-list get through.
        self.control, self.experience, self.weights, self.telemetry = (
            open_channel(ctx, name, "bind", endpoints[name], self.security, bind_host)
            for name in ("control", "experience", "weights", "telemetry"))

    # -- state --------------------------------------------------------------------------------------
    def _resume(self) -> None:
        state = self.rd.load_checkpoint("learner")
        if state is None:
            raise ValueError(f"--resume: no learner checkpoint in {self.rd.path}")
        self.core.load_state_dict(state["core"])
        self.weights_version = int(state["weights_version"])
        torch.set_rng_state(state["torch_rng"])
        # The run's clock goes on from the checkpoint's running time: a curve's minutes stay the run's own,
        # not the minutes since its last restart (the downtime in between is not counted).
        self.started = time.time() - float(state.get("elapsed_s", 0.0))
        log.info("resumed at %d frames, %d updates", self.core.frames, self.core.updates)

    def checkpoint(self) -> None:
        state = {"core": self.core.state_dict(with_replay=self.cfg.replay.checkpoint_replay),
                 "weights_version": self.weights_version, "torch_rng": torch.get_rng_state(),
                 "elapsed_s": time.time() - self.started, "config": self.cfg.to_dict()}
        self.rd.save_checkpoint("learner", state)

    # -- control ------------------------------------------------------------------------------------
    def _send(self, identity: bytes, msg_type: str, fields: dict) -> None:
        # Non-blocking: a peer that does not read its control socket loses this reply; it will ask again.
        sockets.send_routed(self.control, identity, codec.encode(msg_type, fields, sender="learner"), zmq.NOBLOCK)

    def _welcome(self, identity: bytes, index: int) -> None:
        eps = self.endpoints
        if self.relabeler_endpoint is not None:
            eps = eps.with_endpoint("episodes", self.relabeler_endpoint)
        self._send(identity, "welcome", {"config": self.cfg.to_dict(), "endpoints": eps.as_dict(),
                                         "protocol": PROTOCOL_VERSION, "index": index})

    def _capacity(self, role: str) -> int | None:
        """How many of a role the run has numbers for (actors: the config's count; dashboards: any)."""
        return {"actor": self.cfg.actors, "relabeler": 1}.get(role)

    def handle_control(self, identity: bytes, msg) -> None:
        f = msg.fields
        if msg.type == "hello":
            if f["protocol"] != PROTOCOL_VERSION:
                self._refuse_version_to(identity, f["protocol"])
                return
            if f["role"] not in ("actor", "relabeler", "dashboard"):
                self._send(identity, "refuse", {"reason": f"unknown role {f['role']!r}"})
                return
            try:
                index = self.registry.assign(f["role"], identity, f["index"], self._capacity(f["role"]))
            except NoSlot as e:
                self._send(identity, "refuse", {"reason": str(e)})
                return
            self.registry.hello(f["role"], index, identity, f["host"], f["pid"])
            if f["role"] == "actor" and self.relabeler_endpoint is None:
                if (identity, index) not in self.pending_hellos:  # answered once the relabeler registers
                    self.pending_hellos.append((identity, index))
            else:
                self._welcome(identity, index)
            return
        info = self.registry.seen(identity)
        if info is None:
            # Only a peer that said hello is heard. A role that joined before this learner restarted
            # is asked to say hello again (the client does so on this reply).
            self.rejects.add("unknown_peer")
            self._send(identity, "refuse", {"reason": REJOIN})
            return
        if msg.type == "register":  # repeated by the relabeler, so a restarted learner learns it again
            if info.role != "relabeler":
                self.rejects.add("field")
                return
            try:
                self.endpoints.with_endpoint("episodes", f["endpoint"])
            except ValueError:
                self.rejects.add("field")
                return
            self.relabeler_endpoint = f["endpoint"]
            for ident, index in self.pending_hellos:
                self._welcome(ident, index)
            self.pending_hellos.clear()
        elif msg.type == "heartbeat":
            info.stopped = f["state"] == "stopping"
            info.stats.update(f["counters"])
            info.pid = int(f["counters"].get("pid", info.pid))
        elif msg.type == "stats":
            info.stats.update(f["values"])
            for key in ("success_rate_eval_train", "success_rate_eval_heldout",
                        "success_rate_eval_train_se", "success_rate_eval_heldout_se"):
                if f["values"].get(key) is not None:
                    self.eval[key] = f["values"][key]
        else:
            self.rejects.add("unexpected_type")

    def _refuse_version(self, err: codec.WireError, identity: bytes | None) -> None:
        """A peer of another protocol version cannot be decoded, but it can be told why."""
        if err.reason == "version" and identity is not None:
            self._refuse_version_to(identity, err.peer_version)

    def _refuse_version_to(self, identity: bytes, peer_version) -> None:
        self._send(identity, "refuse", {
            "reason": f"protocol version mismatch: this learner speaks {PROTOCOL_VERSION}, the peer "
                      f"speaks {peer_version}; run the same higher-dist version everywhere",
            "protocol": PROTOCOL_VERSION})

    def poll_control(self, limit: int = 100) -> None:
        for _ in range(limit):
            if not self.control.getsockopt(zmq.EVENTS) & zmq.POLLIN:
                return
            routed = sockets.recv_routed(self.control, 0, self.rejects, "control", self._refuse_version)
            if routed is not None:
                self._guarded(self.handle_control, routed[1], *routed)

    def poll_experience(self, limit: int = 4) -> None:
        for _ in range(limit):
            if not self.core.wants_experience():
                return
            msg = sockets.recv_message(self.experience, 0, self.rejects, "experience")
            if msg is None:
                if not self.experience.getsockopt(zmq.EVENTS) & zmq.POLLIN:
                    return
                continue
            if msg.type != "episodes":
                self.rejects.add("unexpected_type")
                continue
            self._guarded(self.take_episodes, msg, msg)

    def take_episodes(self, msg) -> None:
        try:
            episodes = unpack_episodes(
                msg, self.core.spec, reject=lambda reason: self.rejects.add(reason, where="experience"),
                # No bound on the episodes' weights versions: after a learner restart without a
                # checkpoint, honest actors still act with the previous instance's newer versions.
                allow_relabelled=msg.sender == "relabeler", n_actors=self.cfg.actors)
        except codec.WireError as e:
            self.rejects.add(e.reason, e.detail, "experience")
            return
        self.core.add_episodes(episodes)

    def _guarded(self, handler, msg, *args) -> None:
        """Run one message's handler; an unexpected exception is logged with the message's type and
        sender, counted, and the loop goes on (no peer can end this process)."""
        try:
            handler(*args)
        except Exception as exc:  # noqa: BLE001 - the point is to survive anything one message does
            self.handler_errors += 1
            self.rejects.add("handler_error", f"{msg.type} from {msg.sender!r}: {type(exc).__name__}: {exc}")
            log.exception("handling a %s message from %r failed; dropped it", msg.type, msg.sender)

    # -- outputs ------------------------------------------------------------------------------------
    def publish_weights(self) -> None:
        self.weights_version = self.core.updates
        self.weights.send(codec.encode_weights(self.weights_version, self.core.dqn.weights_numpy(),
                                               frames=self.core.frames))

    def maybe_evaluate(self) -> None:
        if self.evaluation.due(self.core.frames):
            self.start_evaluation()

    def start_evaluation(self) -> None:
        dqn = self.core.dqn
        self.evaluator.start(dqn.weights_numpy(), self.core.frames, dqn.average_weights_numpy())

    def _own_row(self) -> dict:
        return {"role": "learner", "id": 0, "host": socket.gethostname(), "pid": os.getpid(), "state": "alive",
                "heartbeat_age_s": 0.0, "frames_per_s": None, "weights_lag": 0,
                "restarts": int(os.environ.get("HIGHER_RESTARTS", "0")), "rejected": self.rejects.total}

    def record(self) -> dict:
        elapsed = time.time() - self.started
        r = self.core.metrics()
        roles = [self._own_row()] + self.registry.table(self.weights_version)
        relabeler = next((i.stats for i in self.registry.roles.values() if i.role == "relabeler"), {})
        actors = [i for i in self.registry.roles.values() if i.role == "actor"]
        actor_rows = [row for row in roles if row["role"] == "actor"]
        actor_fps = [row["frames_per_s"] or 0.0 for row in actor_rows if row["state"] == "alive"]
        lags = [row["weights_lag"] for row in actor_rows if row["weights_lag"] is not None]
        eps = [i.stats["epsilon_mean"] for i in actors if i.stats.get("epsilon_mean") is not None]
        by_reason = self.rejects.counts()
        for info in self.registry.roles.values():  # the other roles report theirs as reject_<reason>
            for key, value in info.stats.items():
                if key.startswith(REJECT_STAT_PREFIX) and isinstance(value, (int, float)):
                    reason = key[len(REJECT_STAT_PREFIX):]
                    by_reason[reason] = by_reason.get(reason, 0) + int(value)
        r.update({
            m.ELAPSED_S: round(elapsed, 1), m.PRESET: self.cfg.preset, m.WORLD: self.cfg.world.name,
            m.FRAMES_BUDGET: self.cfg.frames, m.WEIGHTS_VERSION: self.weights_version,
            m.FRAMES_PER_S: round(sum(actor_fps), 1), m.UPDATES_PER_S: round(self.updates_rate(self.core.updates), 2),
            m.WEIGHTS_LAG_MEAN: round(float(np.mean(lags)), 1) if lags else None,
            m.REJECTED: sum(by_reason.values()), m.LEARNER_REJECTED: self.rejects.total,
            m.REJECTS_BY_REASON: by_reason, m.HANDLER_ERRORS: self.handler_errors,
            **m.relabel_record(relabeler), m.RELABELS_PER_S: relabeler.get("relabels_per_s"),
            m.EPSILON_MEAN: round(float(np.mean(eps)), 4) if eps else None,
            **self.evaluator.latest(), m.ROLES: roles,
        })
        return plain_record(r)

    # -- loop ---------------------------------------------------------------------------------------
    def run(self) -> int:
        stop = []
        for s in (signal.SIGINT, signal.SIGTERM):
            signal.signal(s, lambda *_: stop.append(1))
        self.publish_weights()
        last_weights = last_tel = last_metrics = last_ckpt = time.time()
        poller = zmq.Poller()
        poller.register(self.control, zmq.POLLIN)
        poller.register(self.experience, zmq.POLLIN)
        try:
            while not stop and self.core.frames < self.cfg.frames:
                can_update = self.core.can_update()
                poller.poll(0 if can_update else 20)
                self.poll_control()
                self.poll_experience()
                before = self.core.updates
                self.core.train_available(max_updates=4)
                now = time.time()
                if self.agent.weights_due(before, self.core.updates) or now - last_weights > WEIGHTS_REPUBLISH_S:
                    self.publish_weights()
                    last_weights = now
                self.maybe_evaluate()
                if now - last_tel > TELEMETRY_EVERY_S:
                    last_tel = now
                    record = self.record()
                    self.telemetry.send(codec.encode("telemetry", {"record": record}, sender="learner")[0],
                                        flags=zmq.NOBLOCK)
                    if now - last_metrics > self.cfg.stats_every_s:
                        last_metrics = now
                        self.rd.append_metrics(record)
                if now - last_ckpt > self.cfg.checkpoint_every_s:
                    last_ckpt = now
                    self.checkpoint()
            self.stop_reason = "frame budget reached" if not stop else "stopped by signal"
        finally:
            self.shutdown()
        return 0

    def shutdown(self) -> None:
        for identity in self.registry.identities():
            self._send(identity, "stop", {"reason": self.stop_reason or "learner exiting"})
        try:
            self.telemetry.send(codec.encode("stop", {"reason": self.stop_reason or "learner exiting"},
                                             sender="learner")[0], flags=zmq.NOBLOCK)
        except zmq.ZMQError:
            pass
        self.evaluator.wait()
        if self.core.frames >= self.cfg.frames:  # the run's last point: greedy success at its end
            self.start_evaluation()
            self.evaluator.wait()
        record = self.record()
        self.rd.append_metrics(record)
        self.checkpoint()
        for s in (self.control, self.experience, self.weights, self.telemetry):
            s.close(linger=200)
        self.security.close()
        log.info("learner stopped: %s", self.stop_reason)


def run_learner(cfg: Config, endpoints: Endpoints, run_dir: str, resume: bool = False,
                bind_host: str | None = None, security: Security | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    config_mod.validate(cfg)
    return LearnerRole(cfg, endpoints, run_dir, resume, bind_host, security).run()
