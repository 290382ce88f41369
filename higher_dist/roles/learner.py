"""The learner role: the head of the cluster.

A short loop around `Learner`: answer control messages (roles/control_server.py), take episode
batches while the samples-per-insert ratio allows (otherwise the sockets' high-water marks push back on
the relabeler and the actors), run DQN updates, publish weights, start greedy evaluations on a
background thread, write metrics and telemetry, checkpoint. Ends when the frame budget is reached or on
SIGTERM/SIGINT.

No input can end the loop: every incoming episode is checked against the run's `WorldSpec` where it is
unpacked (wire/episodes.py) and dropped, counted by reason, when it fails; an unexpected exception while
checking one message is logged with the message's type and sender, counted as `handler_error`, and the
loop goes on (roles/loop.HandlerGuard). Relabelled episodes are accepted only in messages whose sender
is the relabeler: an actor never relabels, so such a claim from anyone else is dropped as
`relabel_origin`.

An exception of the learner's own code once a message has passed its checks (the replay insert, a DQN
update, weights publishing, the evaluation thread, metrics, a checkpoint write, handling a control
message) is an internal error, not a bad message: the learner stops at once with one line on stderr
naming the step and the error, exit status 70 (roles/loop.INTERNAL_ERROR_EXIT), and writes neither a
metrics record nor a checkpoint from the state that raised: its last good checkpoint stays on disk as it
was, for the launcher, systemd or a Slurm requeue to resume from. Like a killed learner, it tells no
other role to stop: they reconnect to the restarted one.
"""
from __future__ import annotations

import logging
import os
import signal
import socket
import time

import torch
import zmq

from higher_dist import config as config_mod
from higher_dist import metrics as m
from higher_dist.config import Config
from higher_dist.launch.channels import check_binds, open_channel
from higher_dist.launch.layout import available_cores, learner_alone
from higher_dist.launch.topology import Endpoints
from higher_dist.learning.agent import AgentBuilder
from higher_dist.learning.devices import resolve_device
from higher_dist.learning.episode import Withheld
from higher_dist.roles.control_server import ControlServer
from higher_dist.roles.evaluator import BackgroundEvaluator
from higher_dist.roles.loop import Every, HandlerGuard, internal, stop_on_internal_error
from higher_dist.roles.registry import RateMeter, RoleRegistry
from higher_dist.rundir import RunDir, load_or_refuse, plain_record
from higher_dist.wire import codec, sockets
from higher_dist.wire.episodes import unpack_episodes, withheld_in
from higher_dist.wire.security import Security

log = logging.getLogger("higher.learner")
TELEMETRY_EVERY_S = 0.5
WEIGHTS_REPUBLISH_S = 2.0  # late subscribers (a restarted actor) get weights within this time


class LearnerService:
    def __init__(self, cfg: Config, endpoints: Endpoints, run_dir: str, resume: bool = False,
                 bind_host: str | None = None, security: Security | None = None, threads: int | None = None,
                 layout: str | None = None):
        # The launcher passes its host layout's share; a learner started alone takes its host's cores.
        threads = threads or learner_alone(available_cores(), str(resolve_device(cfg.device)), cfg.torch_threads)
        torch.set_num_threads(threads)
        self.layout = layout or f"learner alone: {threads} thread{'s' if threads != 1 else ''}"
        self.cfg, self.endpoints = cfg, endpoints
        # Without keys, every port bound beyond loopback is named at once, before anything is written:
        # refused, or warned about under --insecure.
        self.security = security or Security()
        check_binds(endpoints, bind_host, self.security, binder="learner")
        self.rd = RunDir(run_dir, tensorboard=cfg.tensorboard)
        self.agent = AgentBuilder(cfg)
        torch.manual_seed(self.agent.seeds.learner_torch)  # this process's RNG, as the runner seeds it
        self.core = self.agent.learner()
        self.evaluator = BackgroundEvaluator(self.agent)
        self.registry = RoleRegistry(dead_after_s=cfg.role_grace_s)
        self.rejects = sockets.RejectCounter()
        self.guard = HandlerGuard(self.rejects, log, "experience")
        self.weights_version = 0
        self.stop_reason = ""
        self.started = time.time()
        self.updates_rate = RateMeter()
        self.resumed = resume
        if resume:
            self._resume()
        elif self.rd.checkpoint_path("learner").exists():
            raise ValueError(f"--run-dir {self.rd.path} already holds a run: add --resume to continue it, "
                             "or choose another --run-dir")
        self.evaluation = self.agent.evaluation_cadence(self.core.frames)
        self.rd.write_config(cfg)
        ctx = zmq.Context.instance()
        # With keys, every socket is a CURVE server and only clients on the allow-list get through.
        self.control = ControlServer(ctx, cfg, endpoints, self.security, bind_host, self.registry, self.rejects)
        self.experience, self.weights, self.telemetry = (
            open_channel(ctx, name, "bind", endpoints[name], self.security, bind_host)
            for name in ("experience", "weights", "telemetry"))

    # -- state --------------------------------------------------------------------------------------
    def _resume(self) -> None:
        state = self.rd.load_checkpoint("learner")
        if state is None:
            raise ValueError(f"--resume: no learner checkpoint in {self.rd.path}")
        load_or_refuse(self.rd.checkpoint_path("learner"), "network", lambda: self.core.load_state_dict(state["core"]))
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

    # -- inputs -------------------------------------------------------------------------------------
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
            checked = self.guard(msg, self.check_episodes, msg)
            if checked is not None and (checked[0] or checked[1] != Withheld()):
                with internal("replay insert"):
                    self.core.add_episodes(*checked)

    def check_episodes(self, msg) -> tuple[list, Withheld]:
        """The message's episodes that pass the checks against the run's world, and the originals its
        sender (the relabeler) kept out of the replay; a WireError drops it all."""
        return unpack_episodes(
            msg, self.core.spec, reject=lambda reason: self.rejects.add(reason, where="experience"),
            # No bound on the episodes' weights versions: after a learner restart without a
            # checkpoint, honest actors still act with the previous instance's newer versions.
            allow_relabelled=msg.sender == "relabeler", n_actors=self.cfg.actors), withheld_in(msg)

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
        return {m.ROW_ROLE: "learner", m.ROW_ID: 0, m.ROW_HOST: socket.gethostname(), m.ROW_PID: os.getpid(),
                m.ROW_STATE: "alive", m.ROW_HEARTBEAT_AGE: 0.0, m.FRAMES_PER_S: None, m.ROW_WEIGHTS_LAG: 0,
                m.ROW_RESTARTS: int(os.environ.get("HIGHER_RESTARTS", "0")), m.ROW_REJECTED: self.rejects.total}

    def record(self) -> dict:
        r = self.core.metrics()
        r.update({
            m.ELAPSED_S: round(time.time() - self.started, 1), m.PRESET: self.cfg.preset,
            m.WORLD: self.cfg.world.name, m.LAYOUT: self.layout, m.FRAMES_BUDGET: self.cfg.frames, m.WEIGHTS_VERSION: self.weights_version,
            m.UPDATES_PER_S: round(self.updates_rate(self.core.updates), 2),
            m.LEARNER_REJECTED: self.rejects.total, m.HANDLER_ERRORS: self.guard.errors,
            **self.evaluator.latest(),
            **self.registry.telemetry(self._own_row(), self.weights_version, self.rejects.counts()),
        })
        return plain_record(r)

    # -- loop ---------------------------------------------------------------------------------------
    def run(self) -> int:
        if self.core.frames >= self.cfg.frames:
            # A restart of a run that is over (a reboot under systemd, a requeue): say so and leave the run
            # as it ended, with no second final evaluation, record or checkpoint.
            self.stop_reason = f"the run already reached its budget ({self.core.frames} of {self.cfg.frames} frames)"
            log.info("nothing to do: %s", self.stop_reason)
            self.control.stop_all(self.stop_reason)
            self._close()
            return 0
        stop = []
        for s in (signal.SIGINT, signal.SIGTERM):
            signal.signal(s, lambda *_: stop.append(1))
        try:
            self.loop(stop)
            self.stop_reason = "frame budget reached" if not stop else "stopped by signal"
            self.shutdown()
        except Exception as exc:  # noqa: BLE001 - the learner's own code raised: see the module's docstring
            return self.stop_on_internal_error(exc)
        return 0

    def loop(self, stop: list) -> None:
        """Until the frame budget is reached or `stop` fills; each step of the learner's own work is named,
        so an exception in it stops the learner with that name (roles/loop.internal)."""
        with internal("weights publishing"):
            self.publish_weights()
        if self.resumed:
            # The curve's first point after a resume is the checkpoint itself, written before any new
            # experience is taken, so where the run went on from is on record rather than inferred.
            with internal("metrics"):
                self.rd.append_metrics(self.record())
        republish, telemetry = Every(WEIGHTS_REPUBLISH_S), Every(TELEMETRY_EVERY_S)
        metrics, checkpoints = Every(self.cfg.stats_every_s), Every(self.cfg.checkpoint_every_s)
        poller = zmq.Poller()
        poller.register(self.control.sock, zmq.POLLIN)
        poller.register(self.experience, zmq.POLLIN)
        while not stop and self.core.frames < self.cfg.frames:
            can_update = self.core.can_update()
            poller.poll(0 if can_update else 20)
            with internal("control message handling"):  # decoding is checked and counted inside, never raises
                self.control.poll()
            self.poll_experience()
            before = self.core.updates
            with internal("DQN update"):
                self.core.train_available(max_updates=4)
            now = time.time()
            if self.agent.weights_due(before, self.core.updates) or republish.due(now):
                with internal("weights publishing"):
                    self.publish_weights()
                republish.reset(now)
            with internal("evaluation"):
                self.evaluator.check()
                self.maybe_evaluate()
            if telemetry(now):
                with internal("metrics"):
                    record = self.record()
                    self.telemetry.send(codec.encode("telemetry", {"record": record}, sender="learner")[0],
                                        flags=zmq.NOBLOCK)
                    if metrics(now):
                        self.rd.append_metrics(record)
            if checkpoints(now):
                with internal("checkpoint writing"):
                    self.checkpoint()

    def shutdown(self) -> None:
        """A clean stop: the run's last point and its final checkpoint, then every role told why. Told only
        after the writes, so that when one fails (an internal error) the others are still there for the
        restarted learner, as after any crash."""
        self.evaluator.wait()
        with internal("evaluation"):
            if self.core.frames >= self.cfg.frames:  # the run's last point: greedy success at its end
                self.start_evaluation()
                self.evaluator.wait()
            self.evaluator.check()
        with internal("metrics"):
            self.rd.append_metrics(self.record())
        with internal("checkpoint writing"):
            self.checkpoint()
        self.control.stop_all(self.stop_reason)
        try:
            self.telemetry.send(codec.encode("stop", {"reason": self.stop_reason}, sender="learner")[0],
                                flags=zmq.NOBLOCK)
        except zmq.ZMQError:
            pass
        self._close()
        log.info("learner stopped: %s", self.stop_reason)

    def stop_on_internal_error(self, exc: Exception) -> int:
        # Like a crash, it tells nobody to stop: the restarted learner finds the actors and the relabeler
        # still there, reconnecting (told to stop, they would exit for good). Nothing of the state that
        # raised is written, no metrics record and no checkpoint: the last good checkpoint is the restart's.
        self.evaluator.wait()
        self._close()
        path = self.rd.checkpoint_path("learner")
        kept = f"last good checkpoint kept: {path}" if path.exists() else "no checkpoint written yet"
        return stop_on_internal_error("learner", exc, kept, log)

    def _close(self) -> None:
        self.control.close()
        for s in (self.experience, self.weights, self.telemetry):
            s.close(linger=200)
        self.security.close()


def run_learner(cfg: Config, endpoints: Endpoints, run_dir: str, resume: bool = False,
                bind_host: str | None = None, security: Security | None = None, threads: int | None = None,
                layout: str | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    config_mod.validate(cfg)
    return LearnerService(cfg, endpoints, run_dir, resume, bind_host, security, threads, layout).run()
