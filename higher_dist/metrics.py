"""The names of every metric a run reports, in one place, with what each means.

The learner's record (metrics.jsonl, telemetry, TensorBoard), the single-process runner, the dashboard,
`higher-plot` and the end-of-run summary all use these names, so a renamed metric cannot silently
disappear from one of them. Pure: no sockets, no rich.
"""
from __future__ import annotations

# Every key has one comment: its meaning, then its unit in [brackets]. docs/metrics.md is generated from
# these (`make docs`). A record is one line of metrics.jsonl (and one telemetry message, one TensorBoard step).

# -- progress -------------------------------------------------------------------------------------
TIME = "time"  # when the record was written (Unix time) [s]
FRAMES = "frames"  # env frames of original episodes the learner took in: the run's clock [frames]
FRAMES_BUDGET = "frames_budget"  # the run's frame budget (`frames` in the config) [frames]
UPDATES = "updates"  # DQN updates done [count]
EPISODES = "episodes"  # original episodes the learner took in [count]
ELAPSED_S = "elapsed_s"  # the run's running time, carried across resumes [s]
PRESET = "preset"  # the paper's method this run is [name]
WORLD = "world"  # the world's name [name]
LAYOUT = "layout"  # how the learner's host shares its cores between the roles (launch/layout.py), as text
FRAMES_PER_S = "frames_per_s"  # each live actor's env frames/s since its start, summed; not a current rate [frames/s]
UPDATES_PER_S = "updates_per_s"  # DQN updates per second [1/s]
WEIGHTS_VERSION = "weights_version"  # the version of the weights last published (its update count) [count]
WEIGHTS_LAG_MEAN = "weights_lag_mean"  # how many updates behind the actors' weights are, on average [updates]
EPSILON_MEAN = "epsilon_mean"  # mean exploration epsilon over the actors' environments [probability]

# -- success --------------------------------------------------------------------------------------
# Greedy evaluation (epsilon 0, one episode per environment) is the headline; training success mixes
# environments exploring at their epsilons and is reported as such.
SUCCESS_EVAL_TRAIN = "success_rate_eval_train"  # greedy success on training goals, latest evaluation [fraction]
SUCCESS_EVAL_HELDOUT = "success_rate_eval_heldout"  # greedy success on held-out goals, latest evaluation [fraction]
# Of the same greedy episodes, those that achieved nothing and ended in a cycle: the policy's input
# repeated, so it repeated its actions until the time-out (learning/episode_ends.py).
CYCLING_EVAL_TRAIN = "cycling_rate_eval_train"  # share of the greedy episodes on training goals that ended in a cycle [fraction]
CYCLING_EVAL_HELDOUT = "cycling_rate_eval_heldout"  # share of the greedy episodes on held-out goals that ended in a cycle [fraction]
SUCCESS_TRAIN = "success_rate_train"  # success of the episodes the learner took in, while exploring [fraction]
EVAL_FRAMES = "eval_frames"  # env frames the evaluated weights had seen (every record repeats the latest) [frames]
SE_SUFFIX = "_se"  # + on an evaluation key: its standard error, sqrt(p (1 - p) / episodes) [fraction]
# With dqn.average_tau > 0 the same evaluation (same goals) also scores the moving average of the
# online weights, under the same names + this suffix (before any _se).
AVERAGED_SUFFIX = "_averaged"  # + on an evaluation key: the same evaluation of the averaged weights [fraction]
# The full names, so that a search for one finds it (docs/metrics.md lists each).
SUCCESS_EVAL_TRAIN_SE = SUCCESS_EVAL_TRAIN + SE_SUFFIX  # standard error of success_rate_eval_train [fraction]
SUCCESS_EVAL_HELDOUT_SE = SUCCESS_EVAL_HELDOUT + SE_SUFFIX  # standard error of success_rate_eval_heldout [fraction]
SUCCESS_EVAL_TRAIN_AVERAGED = SUCCESS_EVAL_TRAIN + AVERAGED_SUFFIX  # greedy success of the averaged weights on training goals [fraction]
SUCCESS_EVAL_HELDOUT_AVERAGED = SUCCESS_EVAL_HELDOUT + AVERAGED_SUFFIX  # greedy success of the averaged weights on held-out goals [fraction]
SUCCESS_EVAL_TRAIN_AVERAGED_SE = SUCCESS_EVAL_TRAIN_AVERAGED + SE_SUFFIX  # standard error of success_rate_eval_train_averaged [fraction]
SUCCESS_EVAL_HELDOUT_AVERAGED_SE = SUCCESS_EVAL_HELDOUT_AVERAGED + SE_SUFFIX  # standard error of success_rate_eval_heldout_averaged [fraction]
CYCLING_EVAL_TRAIN_AVERAGED = CYCLING_EVAL_TRAIN + AVERAGED_SUFFIX  # share of the averaged weights' greedy episodes on training goals that ended in a cycle [fraction]
CYCLING_EVAL_HELDOUT_AVERAGED = CYCLING_EVAL_HELDOUT + AVERAGED_SUFFIX  # share of the averaged weights' greedy episodes on held-out goals that ended in a cycle [fraction]

# -- replay and learning --------------------------------------------------------------------------
REPLAY_SIZE = "replay_size"  # transitions in the replay [transitions]
REPLAY_RATIO = "replay_ratio"  # samples drawn per insert so far (the rate limiter's measure) [samples/insert]
RELABELLED_EPISODES = "relabelled_episodes"  # relabelled copies the learner took in [count]
REPLAY_ORIGIN_PREFIX = "replay_"  # + success, wrong_pick, timeout or relabelled: transitions by origin [transitions]
# The DQN step's own metrics (learning/dqn.py), carried into the record as they come.
LOSS = "loss"  # DQN loss of the last update (Huber, importance-weighted) [loss]
Q_MEAN = "q_mean"  # mean Q of the actions taken, last batch [return]
TD_ABS_MEAN = "td_abs_mean"  # mean |TD error|, last batch [return]
TARGET_MEAN = "target_mean"  # mean n-step target, last batch [return]
GRAD_NORM = "grad_norm"  # gradient norm before clipping, last update [norm]
LEARNING_RATE = "learning_rate"  # the optimiser's, as of the last update (dqn.lr_decay_frames) [lr]
SKIPPED_UPDATES = "skipped_updates"  # steps refused for a non-finite gradient [count]
LOSS_COMPILED = "loss_compiled"  # 1 once the update runs the torch.compile'd loss [flag]
COMPILE_PENDING = "compile_pending"  # 1 while that compile runs in the background (updates run eager) [flag]
# What one DQN update reports (DQNUpdater.update), each key every time.
DQN_KEYS = (LOSS, Q_MEAN, TD_ABS_MEAN, TARGET_MEAN, GRAD_NORM, SKIPPED_UPDATES, COMPILE_PENDING, LOSS_COMPILED)

# -- relabelling ----------------------------------------------------------------------------------
# A relabel strategy's `metrics()` (learning/hindsight/relabel.py) reports these keys, every one, None
# where the strategy has no such thing (the expert has no generator); the record carries them as they come.
RELABEL_STRATEGY = "relabel_strategy"  # what relabels wrong picks: none, expert, noisy or learned [name]
RELABEL_CONSIDERED = "relabel_considered"  # wrong picks handed to the strategy [count]
RELABELS_MADE = "relabels_made"  # relabelled copies the strategy made [count]
RELABEL_ACCURACY = "relabel_accuracy"  # relabels that name the picked object, last relabel.RECENT_RELABELS [fraction]
RELABEL_ACCURACY_TOTAL = "relabel_accuracy_total"  # the same since the start of the run [fraction]
RELABEL_CONTRADICTING = "relabel_contradicting"  # learned relabels naming the failed goal, dropped [count]
RELABEL_UNPARSEABLE = "relabel_unparseable"  # generated instructions the grammar cannot parse, dropped [count]
RELABEL_UNSURE = "relabel_unsure"  # learned relabels too few of the generator's draws agreed with (generator.min_agreement), dropped [count]
RELABEL_GATED_OFF = "relabel_gated_off"  # wrong picks offered while the generator's gate was shut (held ones: relabel_held) [count]
RELABEL_HELD = "relabel_held"  # failed episodes kept while the gate is shut, waiting to be relabelled [count]
RELABEL_WITHHELD = "relabel_withheld"  # failed episodes kept out of the replay while the gate was shut [count]
RELABEL_GATE_OPEN = "relabel_gate_open"  # whether the generator relabels yet (enough pairs and accuracy) [flag]
RELABEL_DATASET_SIZE = "relabel_dataset_size"  # (view, instruction) pairs in the generator's dataset [pairs]
GENERATOR_VAL_ACCURACY = "generator_val_accuracy"  # generator exact match on its validation pairs, latest [fraction]
GENERATOR_VAL_AT_PAIRS = "generator_val_at_pairs"  # dataset size at that evaluation [pairs]
GENERATOR_TRAIN_STEPS = "generator_train_steps"  # the generator's training updates [count]
GENERATOR_EVALUATIONS = "generator_evaluations"  # the generator's validation measurements [count]
GENERATOR_LOSS = "generator_loss"  # the generator's training loss, last update [loss]
RELABEL_KEYS = (RELABEL_STRATEGY, RELABEL_CONSIDERED, RELABELS_MADE, RELABEL_ACCURACY, RELABEL_ACCURACY_TOTAL,
                RELABEL_CONTRADICTING, RELABEL_UNPARSEABLE, RELABEL_UNSURE, RELABEL_GATED_OFF, RELABEL_HELD,
                RELABEL_WITHHELD, RELABEL_GATE_OPEN, RELABEL_DATASET_SIZE,
                GENERATOR_VAL_ACCURACY, GENERATOR_VAL_AT_PAIRS, GENERATOR_TRAIN_STEPS, GENERATOR_EVALUATIONS,
                GENERATOR_LOSS)
# The relabeler service's own (cluster runs only).
RELABELS_PER_S = "relabels_per_s"  # relabelled copies made per second [1/s]
GENERATOR_UPDATES_OWED = "generator_updates_owed"  # generator updates the relabeler is behind its pace; past a few slices it stops reading episodes [updates]
GENERATOR_PACE = "generator_pace"  # generator updates per 1000 env frames the relabeler trains at now (generator.trained_accuracy, gated_updates_per_kframe) [updates/kframe]
# What the record takes from the relabeler's stats (None until the relabeler first reports).
RELABELER_KEYS = RELABEL_KEYS + (RELABELS_PER_S, GENERATOR_UPDATES_OWED, GENERATOR_PACE)

# -- health ---------------------------------------------------------------------------------------
REJECTED = "rejected_messages"  # every role's dropped messages, summed [count]
LEARNER_REJECTED = "learner_rejected"  # messages the learner dropped [count]
REJECTS_BY_REASON = "rejects_by_reason"  # dropped messages over all roles, by reason [{reason: count}]
HANDLER_ERRORS = "handler_errors"  # messages whose checking raised unexpectedly (logged, dropped, loop went on) [count]
ROLES = "roles"  # one row per role, the learner's first, with the columns below [rows]

# -- the roles table: the columns of each row of `roles` ---------------------------------------------
# The roles report to the learner in heartbeats and stats messages (roles/client.py) under the record's
# own names where they mean the same for one role (frames, frames_per_s, weights_version, epsilon_mean,
# success_rate_train, episodes, relabels_made, rejected_messages, handler_errors), plus PID and RESTARTS.
ROW_ROLE = "role"  # learner, actor, relabeler or dashboard [name]
ROW_ID = "id"  # the role's number [index]
ROW_HOST = "host"  # the host it runs on [name]
ROW_PID = "pid"  # its process id [id]
ROW_STATE = "state"  # alive, dead (silent past the heartbeat limit) or stopped [name]
ROW_HEARTBEAT_AGE = "heartbeat_age_s"  # time since it was last heard [s]
ROW_WEIGHTS_LAG = "weights_lag"  # updates its weights are behind the learner's [updates]
ROW_RESTARTS = "restarts"  # times the launcher restarted it [count]
ROW_REJECTED = "rejected"  # messages it dropped [count]
REJECT_STAT_PREFIX = "reject_"  # + a reason: a role's dropped messages under that reason, in its stats [count]
ROLE_ROW_KEYS = (ROW_ROLE, ROW_ID, ROW_HOST, ROW_PID, ROW_STATE, ROW_HEARTBEAT_AGE, FRAMES_PER_S, ROW_WEIGHTS_LAG,
                 ROW_RESTARTS, ROW_REJECTED)

LABELS: dict[str, str] = {
    FRAMES: "env frames",
    SUCCESS_EVAL_TRAIN: "greedy success, training goals",
    SUCCESS_EVAL_HELDOUT: "greedy success, held-out goals",
    SUCCESS_TRAIN: "training success (exploring, epsilon-greedy)",
    SUCCESS_EVAL_TRAIN_AVERAGED: "greedy success of the averaged weights, training goals",
    SUCCESS_EVAL_HELDOUT_AVERAGED: "greedy success of the averaged weights, held-out goals",
    CYCLING_EVAL_TRAIN: "greedy episodes ending in a cycle, training goals",
    GENERATOR_VAL_ACCURACY: "generator exact match (validation)",
    RELABEL_ACCURACY: "relabel accuracy (last 1000 relabels)",
    RELABEL_DATASET_SIZE: "generator pairs",
    RELABEL_GATE_OPEN: "generator gate open",
    REPLAY_RATIO: "samples per insert",
    FRAMES_PER_S: "env frames/s",
    UPDATES_PER_S: "updates/s",
    REJECTED: "rejected messages",
}


def label(name: str) -> str:
    """A human label for a metric name (the name itself where none is declared)."""
    return LABELS.get(name, name.replace("_", " "))


def replay_origin(origin: str) -> str:
    return REPLAY_ORIGIN_PREFIX + origin
