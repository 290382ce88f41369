"""What the dashboard shows, as pure rich renderables: no sockets, no clocks of its own.

The learner's telemetry record is a flat dict (see the keys used below); any key may be missing or
None early in a run, and everything here renders "-" for it rather than raising. Rates (success,
accuracy) are fractions in [0, 1] and are shown as percents.

`DashboardState` keeps the latest record, when it arrived and short histories for the sparklines;
`render(state)` turns it into one renderable, laid out for the terminal's width when drawn: below
WIDE_FROM columns the learning panel gets a row of its own and the role table short headers, so an
80-column terminal shows every figure whole. Keeping rendering pure lets the tests draw a recorded
stream of records into a `Console(record=True)` and read the text back.
"""
from __future__ import annotations

import math
import time
from collections import deque
from typing import Any, Iterable

from rich import box
from rich.console import Group, RenderableType
from rich.panel import Panel
from rich.progress_bar import ProgressBar
from rich.table import Table
from rich.text import Text

from higher_dist import metrics as m

MISSING = "-"
SPARK_BLOCKS = "▁▂▃▄▅▆▇█"
HISTORY_LEN = 120
SPARK_WIDTH = 60
STALE_AFTER_S = 5.0  # the learner publishes several times a second; 5 s of silence means it is gone

# Replay origins, in the order they are stacked, with the colour each one gets in the bar.
REPLAY_ORIGINS = (
    ("replay_success", "success", "green"),
    ("replay_wrong_pick", "wrong pick", "red"),
    ("replay_timeout", "time-out", "yellow"),
    ("replay_relabelled", "relabelled", "cyan"),
)
ROLE_ORDER = {"learner": 0, "relabeler": 1, "actor": 2}
STATE_STYLE = {"alive": "green", "stopped": "yellow", "dead": "bold red"}


# ----------------------------------------------------------------------------------------------
# Formatting: every helper takes Any and returns "-" for None, NaN or a value of the wrong type, so
# a malformed record can never take the dashboard down.

def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def fmt_int(v: Any) -> str:
    return f"{int(v):,}" if _is_number(v) else MISSING


def fmt_float(v: Any, digits: int = 2) -> str:
    return f"{v:.{digits}f}" if _is_number(v) else MISSING


def fmt_pct(v: Any, digits: int = 1) -> str:
    return f"{100.0 * v:.{digits}f}%" if _is_number(v) else MISSING


def fmt_rate(v: Any) -> str:
    """A per-second rate: no decimals once it is large enough for them to be noise."""
    if not _is_number(v):
        return MISSING
    return f"{v:,.0f}/s" if abs(v) >= 100 else f"{v:.2f}/s"


def fmt_duration(seconds: Any) -> str:
    if not _is_number(seconds) or seconds < 0:
        return MISSING
    s = int(round(seconds))
    h, rem = divmod(s, 3600)
    m, s = divmod(rem, 60)
    return f"{h}h{m:02d}m{s:02d}s" if h else (f"{m}m{s:02d}s" if m else f"{s}s")


def sparkline(values: Iterable[Any], width: int, lo: float | None = None, hi: float | None = None) -> str:
    """The last `width` values as unicode blocks ▁..█ scaled to [lo, hi].

    lo/hi default to the data's own min/max; pass a fixed scale (0, 1 for rates) so that a flat
    curve at 90% does not look like one at 10%. Missing values (None, NaN) show as a space; a flat
    series with no fixed scale sits on the lowest block.
    """
    if width <= 0:
        return ""
    tail = list(values)[-width:]
    numbers = [v for v in tail if _is_number(v)]
    if not numbers:
        return " " * len(tail)
    low = min(numbers) if lo is None else lo
    high = max(numbers) if hi is None else hi
    span = high - low
    top = len(SPARK_BLOCKS) - 1
    out = []
    for v in tail:
        if not _is_number(v):
            out.append(" ")
            continue
        frac = 0.0 if span <= 0 else (min(max(v, low), high) - low) / span
        out.append(SPARK_BLOCKS[int(round(frac * top))])
    return "".join(out)


# ----------------------------------------------------------------------------------------------

class DashboardState:
    """The latest telemetry record, when it came, and bounded histories for the trends panel."""

    def __init__(self, history_len: int = HISTORY_LEN, stale_after_s: float = STALE_AFTER_S,
                 source: str = ""):
        self.record: dict[str, Any] = {}
        self.records_seen = 0
        self.garbage_frames = 0
        self.last_update: float | None = None  # time.monotonic() of the last record
        self.stale_after_s = stale_after_s
        self.source = source  # the endpoint we listen on, for the "waiting" banner
        self.success_history: deque[Any] = deque(maxlen=history_len)  # greedy evaluation, train goals
        self.exploring_history: deque[Any] = deque(maxlen=history_len)  # training success (exploring)
        self.generator_history: deque[Any] = deque(maxlen=history_len)

    def update(self, record: dict[str, Any], now: float | None = None) -> None:
        if not isinstance(record, dict):
            self.note_garbage()
            return
        self.record = record
        self.records_seen += 1
        self.last_update = time.monotonic() if now is None else now
        # Append even when missing so the sparklines keep time-alignment between the two series.
        self.success_history.append(record.get(m.SUCCESS_EVAL_TRAIN))
        self.exploring_history.append(record.get(m.SUCCESS_TRAIN))
        self.generator_history.append(record.get(m.GENERATOR_VAL_ACCURACY))

    def note_garbage(self) -> None:
        self.garbage_frames += 1

    def age_s(self, now: float | None = None) -> float | None:
        if self.last_update is None:
            return None
        return (time.monotonic() if now is None else now) - self.last_update

    def is_stale(self, now: float | None = None) -> bool:
        age = self.age_s(now)
        return age is not None and age > self.stale_after_s


# ----------------------------------------------------------------------------------------------
# Panels. Each takes the record dict and returns one Panel.

def _kv_table() -> Table:
    t = Table.grid(padding=(0, 2))
    t.add_column(style="bold", no_wrap=True, min_width=16)  # the longest label, never truncated
    t.add_column(no_wrap=True)
    return t


# The role table's columns: (wide header, narrow header, justify). Narrow headers fit 80 columns.
CLUSTER_COLUMNS = (("role", "role", "left"), ("id", "id", "right"), ("host", "host", "left"),
                   ("pid", "pid", "right"), ("state", "state", "left"), ("heartbeat", "beat", "right"),
                   ("frames/s", "frames/s", "right"), ("weights lag", "lag", "right"),
                   ("restarts", "rst", "right"), ("rejected", "rej", "right"))


def cluster_panel(record: dict[str, Any], narrow: bool = False) -> Panel:
    # Narrow: one space between columns and short headers, so a row fits an 80-column terminal; only
    # the host name gives way (with an ellipsis) when it is long.
    table = Table(box=box.SIMPLE_HEAD, expand=True, pad_edge=False,
                  padding=(0, 1, 0, 0) if narrow else (0, 1))
    for wide_name, narrow_name, justify in CLUSTER_COLUMNS:
        table.add_column(narrow_name if narrow else wide_name, justify=justify,
                         no_wrap=True, overflow="ellipsis" if wide_name == "host" else "fold",
                         min_width=None if wide_name == "host" else len(narrow_name if narrow else wide_name))
    roles = record.get(m.ROLES)
    roles = [r for r in roles if isinstance(r, dict)] if isinstance(roles, list) else []
    roles.sort(key=lambda r: (ROLE_ORDER.get(r.get(m.ROW_ROLE), 9), r.get(m.ROW_ID) if _is_number(r.get(m.ROW_ID)) else 0))
    for r in roles:
        state = r.get(m.ROW_STATE)
        # A dead role must jump out: the whole row goes red, the state cell says GONE.
        label = "GONE (dead)" if state == "dead" else (str(state) if state is not None else MISSING)
        age = r.get(m.ROW_HEARTBEAT_AGE)
        restarts = r.get(m.ROW_RESTARTS)
        table.add_row(
            str(r.get(m.ROW_ROLE, MISSING)), fmt_int(r.get(m.ROW_ID)), str(r.get(m.ROW_HOST) or MISSING),
            fmt_int(r.get(m.ROW_PID)).replace(",", ""), Text(label, style=STATE_STYLE.get(state, "")),
            f"{age:.1f} s" if _is_number(age) else MISSING, fmt_rate(r.get(m.FRAMES_PER_S)),
            fmt_int(r.get(m.ROW_WEIGHTS_LAG)),
            Text(fmt_int(restarts), style="yellow" if _is_number(restarts) and restarts > 0 else ""),
            fmt_int(r.get(m.ROW_REJECTED)),
            style="red" if state == "dead" else None,
        )
    if not roles:
        table.add_row(MISSING, *[""] * 9)
    alive = sum(r.get(m.ROW_STATE) == "alive" for r in roles)
    dead = sum(r.get(m.ROW_STATE) == "dead" for r in roles)
    title = f"Cluster  [green]{alive} alive[/]" + (f"  [bold red]{dead} dead[/]" if dead else "")
    subtitle = (f"rejected messages {fmt_int(record.get(m.REJECTED))}"
                f"  ·  weights v{fmt_int(record.get(m.WEIGHTS_VERSION))}")
    reasons = reject_summary(record)
    body: RenderableType = table if not reasons else Group(table, Text(reasons, style="yellow"))
    return Panel(body, title=title, title_align="left", subtitle=subtitle, subtitle_align="right")


def reject_summary(record: dict[str, Any], top: int = 6) -> str:
    """'dropped: mission_grammar 12, outcome 3, ...': what every role dropped, by reason, largest first."""
    by_reason = record.get(m.REJECTS_BY_REASON)
    if not isinstance(by_reason, dict):
        return ""
    counts = sorted(((n, k) for k, n in by_reason.items() if _is_number(n) and n > 0), reverse=True)
    if not counts:
        return ""
    shown = ", ".join(f"{k} {fmt_int(n)}" for n, k in counts[:top])
    more = f", +{len(counts) - top} more reasons" if len(counts) > top else ""
    errors = record.get(m.HANDLER_ERRORS)
    tail = f"; handler errors {fmt_int(errors)}" if _is_number(errors) and errors else ""
    return f"dropped: {shown}{more}{tail}"


def frames_progress(record: dict[str, Any]) -> tuple[RenderableType, str]:
    """(a bar of frames / budget with the percent done, the ETA from the current frame rate)."""
    frames, budget, fps = record.get(m.FRAMES), record.get(m.FRAMES_BUDGET), record.get(m.FRAMES_PER_S)
    if not (_is_number(frames) and _is_number(budget) and budget > 0):
        return Text(MISSING), MISSING
    if frames >= budget:
        eta = "done"
    else:
        eta = fmt_duration((budget - frames) / fps) if _is_number(fps) and fps > 0 else MISSING
    row = Table.grid(padding=(0, 1))
    row.add_column(width=18)
    row.add_column(no_wrap=True)
    row.add_row(ProgressBar(total=budget, completed=min(frames, budget), width=18),
                f"{min(frames / budget, 1.0):.0%}")
    return row, eta


def learning_panel(record: dict[str, Any]) -> Panel:
    t = _kv_table()
    bar, eta = frames_progress(record)
    t.add_row("frames", f"{fmt_int(record.get(m.FRAMES))} / {fmt_int(record.get(m.FRAMES_BUDGET))}")
    t.add_row("", bar)
    t.add_row("ETA", eta)
    t.add_row("frames/s", fmt_rate(record.get(m.FRAMES_PER_S)))
    t.add_row("updates", f"{fmt_int(record.get(m.UPDATES))}  ({fmt_rate(record.get(m.UPDATES_PER_S))})")
    t.add_row("episodes", fmt_int(record.get(m.EPISODES)))
    t.add_row("replay ratio", fmt_float(record.get(m.REPLAY_RATIO), 2))
    t.add_row("loss", fmt_float(record.get(m.LOSS), 4))
    t.add_row("mean Q", fmt_float(record.get(m.Q_MEAN), 3))
    t.add_row("epsilon", fmt_float(record.get(m.EPSILON_MEAN), 3))
    # Greedy evaluation is the headline; the training success mixes slots exploring at up to the
    # largest epsilon of the ladder, so it is labelled as such.
    t.add_row("greedy, train", fmt_eval(record, "success_rate_eval_train"))
    t.add_row("greedy, held-out", fmt_eval(record, "success_rate_eval_heldout"))
    if _is_number(record.get(m.SUCCESS_EVAL_TRAIN_AVERAGED)):  # dqn.average_tau > 0
        t.add_row("greedy, averaged", fmt_eval(record, m.SUCCESS_EVAL_TRAIN_AVERAGED))
    if _is_number(record.get(m.CYCLING_EVAL_TRAIN)):  # most greedy failures are cycles (learning/episode_ends.py)
        t.add_row("greedy, cycling", fmt_pct(record.get(m.CYCLING_EVAL_TRAIN)))
    t.add_row("exploring, train", fmt_pct(record.get(m.SUCCESS_TRAIN)))
    return Panel(t, title="Learning", title_align="left")


def fmt_eval(record: dict[str, Any], key: str) -> str:
    """A greedy success rate with its standard error when the record has one: '47.3% ± 3.1'."""
    rate, se = record.get(key), record.get(key + m.SE_SUFFIX)
    if not _is_number(se):
        return fmt_pct(rate)
    return f"{fmt_pct(rate)} ± {100 * se:.1f}"


def relabeler_panel(record: dict[str, Any]) -> Panel:
    gate = record.get(m.RELABEL_GATE_OPEN)
    gate_text = (Text("open", style="bold green") if gate is True
                 else Text("closed", style="yellow") if gate is False else Text(MISSING))
    t = _kv_table()
    t.add_row("dataset size", fmt_int(record.get(m.RELABEL_DATASET_SIZE)))
    t.add_row("val. accuracy", fmt_pct(record.get(m.GENERATOR_VAL_ACCURACY)))
    t.add_row("gate", gate_text)
    t.add_row("relabels/s", fmt_rate(record.get(m.RELABELS_PER_S)))
    withheld = record.get(m.RELABEL_WITHHELD)
    if _is_number(withheld) and withheld > 0:  # relabel.withheld_while_gated: why the replay grows slowly at first
        t.add_row("kept out (gate shut)", fmt_int(withheld))
    t.add_row("relabelled eps", fmt_int(record.get(m.RELABELLED_EPISODES)))
    t.add_row("relabel accuracy", fmt_pct(record.get(m.RELABEL_ACCURACY)))
    return Panel(t, title="Relabeler", title_align="left")


def replay_panel(record: dict[str, Any], bar_width: int = 30) -> Panel:
    counts = [(label, record.get(key), colour) for key, label, colour in REPLAY_ORIGINS]
    known = [c for _, c, _ in counts if _is_number(c) and c >= 0]
    total = sum(known)
    t = _kv_table()
    t.add_column(justify="right", no_wrap=True)
    t.add_row("size", fmt_int(record.get(m.REPLAY_SIZE)), "")
    for label, count, colour in counts:
        share = count / total if _is_number(count) and total > 0 else None
        t.add_row(Text(label, style=colour), fmt_int(count), fmt_pct(share))
    # A stacked bar of the composition; each origin gets at least one cell if it is present at all.
    bar = Text()
    if total > 0:
        for _, count, colour in counts:
            if _is_number(count) and count > 0:
                bar.append("█" * max(1, round(bar_width * count / total)), style=colour)
    return Panel(Group(t, bar), title="Replay", title_align="left")


def trends_panel(state: DashboardState, width: int = SPARK_WIDTH) -> Panel:
    t = _kv_table()
    t.add_column(no_wrap=True)
    succ = list(state.success_history)
    rows = (("greedy success", succ, "green"), ("exploring success", list(state.exploring_history), "yellow"),
            ("generator acc.", list(state.generator_history), "cyan"))
    for label, values, style in rows:
        last = next((v for v in reversed(values) if _is_number(v)), None)
        t.add_row(label, Text(sparkline(values, width, 0.0, 1.0) or MISSING, style=style), fmt_pct(last))
    return Panel(t, title=f"Trends (last {len(succ)} records, scale 0-100%)", title_align="left")


def header(state: DashboardState, now: float | None = None) -> RenderableType:
    r = state.record
    line = Text()
    line.append("higher-dist", style="bold magenta")
    line.append(f"  preset {r.get(m.PRESET) or MISSING}  world {r.get(m.WORLD) or MISSING}"
                f"  elapsed {fmt_duration(r.get(m.ELAPSED_S))}")
    if state.garbage_frames:
        line.append(f"  garbage frames {state.garbage_frames}", style="yellow")
    if r.get(m.LAYOUT):
        line = Group(line, Text(f"layout  {r.get(m.LAYOUT)}", style="dim"))
    age = state.age_s(now)
    if age is None:
        banner = Text(f"waiting for telemetry{' from ' + state.source if state.source else ''} ...",
                      style="bold yellow")
        return Group(line, banner)
    if state.is_stale(now):
        return Group(line, Text(f"no telemetry for {age:.0f} s: the learner may be gone; "
                                "figures below are the last ones received", style="bold white on red"))
    return line


# Below this width the three middle panels cannot sit side by side without cutting figures (a frames
# count against its budget alone takes 21 columns and more), so the learning panel takes a row of its own.
WIDE_FROM = 140


class Dashboard:
    """The whole dashboard, laid out for the width it is drawn in (rich passes it at render time)."""

    def __init__(self, state: DashboardState, now: float | None = None):
        self.state, self.now = state, now

    def __rich_console__(self, console, options):
        yield layout(self.state, self.now, narrow=options.max_width < WIDE_FROM)


def layout(state: DashboardState, now: float | None, narrow: bool) -> RenderableType:
    r = state.record
    panels = [learning_panel(r), relabeler_panel(r), replay_panel(r)]
    middle = Table.grid(expand=True, padding=(0, 1))
    if narrow:  # learning alone, then relabeler and replay side by side
        middle.add_column(ratio=1)
        middle.add_column(ratio=1)
        rows = Group(panels[0], middle)
        middle.add_row(*panels[1:])
    else:
        for _ in range(3):
            middle.add_column(ratio=1)
        middle.add_row(*panels)
        rows = middle
    spark = SPARK_WIDTH if not narrow else SPARK_WIDTH // 2
    body = Group(header(state, now), cluster_panel(r, narrow), rows, trends_panel(state, spark))
    if state.is_stale(now):
        return Panel(body, border_style="red", title="STALE", title_align="right")
    return body


def render(state: DashboardState, now: float | None = None) -> RenderableType:
    """The whole dashboard for the state's latest record (now: a time.monotonic() value, for tests)."""
    return Dashboard(state, now)
