"""The relabeler role: the instruction generator as a service between the actors and the learner.

Episodes come in on its PULL socket and are checked against the run's world where they are unpacked
(an actor never sends relabelled copies, so one that claims to is dropped); successes feed the
generator's dataset; wrong picks are relabelled by the preset's strategy (learned generator behind its
gate, expert, noisy expert or none); originals and copies go on to the learner. The generator trains at
the pace the config sets per env frame (`generator.updates_per_kframe`, and `trained_updates_per_kframe`
while its validation exact match is at `generator.trained_accuracy` or above; enforced by the builder's
`GeneratorPace` exactly as in the single-process runner), in short slices between messages; when it
falls behind by more than a few slices the relabeler stops reading until it has caught up, which pushes
back on the actors instead of letting the pace depend on the machine. When the learner pushes back (its
socket is full) the relabeler stops reading too. Its generator, dataset and pace are checkpointed.

A message that fails its checks is dropped and counted. An exception of its own work on episodes that
passed (relabelling, generator training, a checkpoint write) stops it with one line naming the step, exit
status 70 and no checkpoint of the state that raised: its last good one stays for --resume (roles/loop.py).
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import zmq

from higher_dist import metrics as m
from higher_dist.launch.channels import open_channel
from higher_dist.learning.agent import AgentBuilder, train_generator
from higher_dist.learning.episode import Withheld
from higher_dist.learning.hindsight.relabel import relabel_batch
from higher_dist.roles.client import start_role
from higher_dist.roles.loop import Every, HandlerGuard, internal, stop_on_internal_error
from higher_dist.rundir import RunDir, load_or_refuse, plain_record
from higher_dist.wire import codec, sockets
from higher_dist.wire.episodes import pack_episodes, unpack_episodes
from higher_dist.wire.security import Security

log = logging.getLogger("higher.relabeler")
CHECKPOINT_EVERY_S = 60.0  # at most; cfg.checkpoint_every_s when that is shorter
TRAIN_SLICE = 5  # generator updates between two looks at the sockets
MAX_BACKLOG = 8 * TRAIN_SLICE  # owed updates beyond which no new episodes are read
WAIT_MS = 20  # longest wait on a socket before looking at control, training and stats again


class RelabelerService:
    """What the service does with one message, apart from the sockets: `check` (what the loop guards: a
    message that fails it is dropped and counted) and `relabel` (its own work: an exception there is an
    internal error that stops the relabeler)."""

    def __init__(self, agent: AgentBuilder, rejects: sockets.RejectCounter):
        self.agent, self.rejects = agent, rejects
        self.strategy = agent.relabel_strategy()
        self.pace = agent.generator_pace()
        self.trainable = self.strategy.name == "learned"  # only the generator has anything to train
        self.received = self.relabelled = 0
        # Kept out of the replay and not yet reported to the learner: only the failures since its last
        # message, which a stop before the next one leaves uncounted (not checkpointed).
        self.withheld_unsent = Withheld()

    def check(self, msg) -> list:
        """The message's episodes that pass the checks against the run's world; a WireError drops it all."""
        return unpack_episodes(msg, self.agent.spec, reject=lambda r: self.rejects.add(r, where="episodes"),
                               allow_relabelled=False, n_actors=self.agent.cfg.actors)

    def relabel(self, episodes: list) -> list | None:
        """The message to forward to the learner: checked episodes the strategy keeps in, their relabelled
        copies, and the count of those it kept out; None while it has nothing to store (the count waits
        for the next message: one carries at least one episode)."""
        self.received += len(episodes)
        stored, withheld = relabel_batch(self.strategy, episodes)
        self.relabelled += len(stored) - len(episodes) + withheld.episodes
        if self.trainable:
            self.pace.add_frames(sum(ep.length for ep in episodes))
        self.withheld_unsent += withheld
        if not stored:
            return None
        fields, arrays = pack_episodes(stored, self.withheld_unsent)
        self.withheld_unsent = Withheld()
        return codec.encode("episodes", fields, arrays, sender="relabeler")

    def train_slice(self) -> None:
        if self.trainable:
            train_generator(self.strategy, self.pace, TRAIN_SLICE)

    @property
    def behind(self) -> bool:
        return self.trainable and self.pace.owed > MAX_BACKLOG

    def state_dict(self) -> dict:
        return {**self.strategy.state_dict(), "pace": self.pace.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        state = dict(state)  # the caller's checkpoint stays as it was loaded
        if "pace" in state:
            self.pace.load_state_dict(state.pop("pace"))
        self.strategy.load_state_dict(state)


DEFAULT_STATE_DIR = Path("runs") / "relabeler"  # its checkpoint without --state-dir (named in its --help)


def restore(service: RelabelerService, rd: RunDir) -> bool:
    """Load the run directory's relabeler checkpoint into `service`; False when there is none. A checkpoint
    whose generator has other shapes (another version's) is refused with a ValueError naming the file."""
    state = rd.load_checkpoint("relabeler")
    if state is None:
        return False
    load_or_refuse(rd.checkpoint_path("relabeler"), "generator", lambda: service.load_state_dict(state))
    return True


def run_relabeler(learner: str, state_dir: str | None = None, resume: bool = False, bind_host: str | None = None,
                  security: Security | None = None, threads: int | None = None, advertise: str | None = None) -> int:
    client, cfg, endpoints, stop = start_role(learner, "relabeler", 0, security, threads)
    service = RelabelerService(AgentBuilder(cfg), client.rejects)
    rd = RunDir(state_dir or DEFAULT_STATE_DIR)
    if resume and restore(service, rd):
        log.info("resumed the relabeler's generator and dataset from %s", rd.checkpoint_path("relabeler"))
    ctx = zmq.Context.instance()
    episodes_endpoint = advertise or endpoints.episodes
    # A CURVE server of its own: the security object starts this process's authenticator on first bind.
    inbox = open_channel(ctx, "episodes", "bind", episodes_endpoint, client.security, bind_host)
    outbox = sockets.PendingSend(open_channel(ctx, "experience", "connect", endpoints.experience, client.security))
    client.send("register", {"role": "relabeler", "endpoint": episodes_endpoint})
    stats, checkpoints = Every(cfg.stats_every_s), Every(min(CHECKPOINT_EVERY_S, cfg.checkpoint_every_s))
    relabels_window = (time.time(), 0)
    guard = HandlerGuard(client.rejects, log, "episodes")

    try:
        while not stop and not client.poll():
            # Wait, briefly, rather than spin: a full outbox is the learner holding its replay ratio.
            outbox.flush(WAIT_MS)
            msg = None
            if not outbox.busy and not service.behind:
                msg = sockets.recv_message(inbox, WAIT_MS, client.rejects, "episodes")
            if msg is not None and msg.type == "episodes":
                episodes = guard(msg, service.check, msg)
                if episodes:
                    with internal("relabelling"):
                        out = service.relabel(episodes)
                        if out is not None:
                            outbox.put(out)
            elif msg is not None:
                client.rejects.add("unexpected_type")
            with internal("generator training"):
                service.train_slice()
            now = time.time()
            client.heartbeat({m.EPISODES: service.received, m.RELABELS_MADE: service.relabelled})
            if stats(now):
                t_w, n_w = relabels_window
                relabels_per_s = (service.relabelled - n_w) / max(now - t_w, 1e-9)
                relabels_window = (now, service.relabelled)
                pace = service.pace.updates_per_kframe if service.trainable else None  # an expert trains nothing
                client.send("register", {"role": "relabeler", "endpoint": episodes_endpoint})
                client.stats(plain_record({**service.strategy.metrics(), m.EPISODES: service.received,
                                           m.RELABELS_MADE: service.relabelled, m.RELABELS_PER_S: round(relabels_per_s, 2),
                                           m.HANDLER_ERRORS: guard.errors, m.GENERATOR_UPDATES_OWED: service.pace.owed,
                                           m.GENERATOR_PACE: pace}))
            if checkpoints(now):
                with internal("checkpoint writing"):
                    rd.save_checkpoint("relabeler", service.state_dict())
        with internal("checkpoint writing"):
            rd.save_checkpoint("relabeler", service.state_dict())
    except Exception as exc:  # noqa: BLE001 - its own code raised: no checkpoint of that state (roles/loop.py)
        path = rd.checkpoint_path("relabeler")
        kept = f"last good checkpoint kept: {path}" if path.exists() else "no checkpoint written yet"
        return stop_on_internal_error("relabeler", exc, kept, log)
    finally:
        inbox.close(linger=0)
        outbox.socket.close(linger=500)
        client.close()
    log.info("relabeler stopped: %d episodes in, %d relabelled", service.received, service.relabelled)
    return 0

