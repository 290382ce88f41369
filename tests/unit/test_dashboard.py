"""The dashboard: rendering of recorded telemetry, sparklines, and the live loop over a real socket."""
from __future__ import annotations

import io
import re
import threading
import time

import msgpack
import pytest
import zmq
from rich.console import Console

from higher_dist.launch.topology import Endpoints
from higher_dist.roles.dashboard import STOP, decode_record, run_dashboard
from higher_dist.wire import encode
from higher_dist.roles.dashboard_view import DashboardState, render, sparkline


def _roles() -> list[dict]:
    return [
        {"role": "actor", "id": 1, "host": "nodeB", "pid": 4321, "state": "dead", "heartbeat_age_s": 31.0,
         "frames_per_s": None, "weights_lag": 7, "restarts": 2, "rejected": 0},
        {"role": "learner", "id": 0, "host": "nodeA", "pid": 1000, "state": "alive", "heartbeat_age_s": 0.1,
         "frames_per_s": None, "weights_lag": None, "restarts": 0, "rejected": 0},
        {"role": "relabeler", "id": 0, "host": "nodeA", "pid": 1001, "state": "alive", "heartbeat_age_s": 0.4,
         "frames_per_s": None, "weights_lag": None, "restarts": 0, "rejected": 3},
        {"role": "actor", "id": 0, "host": "nodeA", "pid": 1002, "state": "alive", "heartbeat_age_s": 0.2,
         "frames_per_s": 812.5, "weights_lag": 1, "restarts": 0, "rejected": 0},
    ]


def recorded_stream(n: int = 10) -> list[dict]:
    """A run as the learner would publish it: early records sparse, later ones complete."""
    stream = [{"time": 1000.0, "elapsed_s": 0.5, "preset": "higher", "frames": 0}]
    for i in range(1, n):
        stream.append({
            "time": 1000.0 + 2 * i, "elapsed_s": 2.0 * i, "preset": "higher", "world": "fetch_attr",
            "frames": 123_456 * i, "frames_budget": 5_000_000, "updates": 1000 * i, "episodes": 50 * i,
            "success_rate_train": i / (n - 1), "success_rate_eval_train": 0.5, "success_rate_eval_heldout": 0.25,
            "success_rate_eval_train_se": 0.031,
            "relabelled_episodes": 10 * i, "generator_val_accuracy": 0.1 * i if i > 2 else None,
            "relabel_dataset_size": 1500, "relabel_gate_open": True, "relabels_per_s": 4.5,
            "relabel_accuracy": 0.8125, "rejected_messages": 3, "frames_per_s": 1500.0, "updates_per_s": 2.5,
            "replay_ratio": 8.0, "loss": 0.01234, "q_mean": 0.4567, "epsilon_mean": 0.1, "replay_size": 1000,
            "replay_success": 200, "replay_wrong_pick": 300, "replay_timeout": 400, "replay_relabelled": 100,
            "weights_version": 42, "roles": _roles(),
        })
    return stream


def export(renderable) -> str:
    console = Console(record=True, width=140, file=io.StringIO(), color_system=None)
    console.print(renderable)
    return console.export_text()


def drawn_panels(text: str) -> dict[str, list[str]]:
    """Each panel of a dashboard drawn as text, by the first word of its title: the rows inside its
    borders (left padding kept, blank rows dropped) and, under TITLE.footer, its bottom border's text."""
    lines = text.splitlines()
    out: dict[str, list[str]] = {}
    for i, line in enumerate(lines):
        for box_top in re.finditer(r"╭─ (\w+)[^╮]*╮", line):
            start, end, rows = box_top.start(), box_top.end(), []
            for below in lines[i + 1:]:
                cell = below[start:end]
                if cell.startswith("╰"):
                    out[f"{box_top.group(1)}.footer"] = [" ".join(cell.strip("╰─╯ ").split())]
                    break
                if cell[1:-1].strip():
                    rows.append(cell[1:-1].rstrip())
            out[box_top.group(1)] = rows
    return out


def figures(rows: list[str]) -> dict[str, str]:
    """A label/value panel's rows as {label: its figures, spaces squeezed}; an unlabelled row (the
    frames bar) is under ""."""
    out = {}
    for row in rows:
        if row[1:2] == " ":
            out[""] = " ".join(row.split())
        else:
            label, value = re.split(r"\s{2,}", row.strip(), maxsplit=1)
            out[label] = " ".join(value.split())
    return out


def role_rows(rows: list[str]) -> list[list[str]]:
    """The cluster panel's role table below its header rule, one list of cells per row."""
    rule = next(i for i, row in enumerate(rows) if set(row.strip()) == {"─"})
    return [re.split(r"\s{2,}", row.strip()) for row in rows[rule + 1:]]


# What each label/value row shows when its record has nothing for it.
NOTHING = {"Learning": {"frames": "- / -", "": "-", "ETA": "-", "frames/s": "-", "updates": "- (-)", "episodes": "-",
                        "replay ratio": "-", "loss": "-", "mean Q": "-", "epsilon": "-", "greedy, train": "-",
                        "greedy, held-out": "-", "exploring, train": "-"},
           "Relabeler": {"dataset size": "-", "val. accuracy": "-", "gate": "-", "relabels/s": "-",
                         "relabelled eps": "-", "relabel accuracy": "-"},
           "Replay": {"size": "-", "success": "- -", "wrong pick": "- -", "time-out": "- -", "relabelled": "- -"},
           "Trends": {"greedy success": "-", "exploring success": "-", "generator acc.": "-"}}


def test_sparkline_known_input():
    assert sparkline(range(8), 8) == "▁▂▃▄▅▆▇█"
    assert sparkline([0.0, 0.5, 1.0], 3, lo=0.0, hi=1.0) == "▁▅█"
    # Only the most recent `width` values are drawn.
    assert sparkline(range(100), 4) == "▁▃▆█"
    assert sparkline([None, 1, float("nan"), 3], 4) == " ▁ █"
    assert sparkline([], 5) == "" and sparkline([1, 2], 0) == ""
    assert sparkline([3, 3, 3], 3) == "▁▁▁"
    assert sparkline([5.0], 1, lo=0, hi=1) == "█"  # clipped to the fixed scale


def test_render_recorded_stream():
    state = DashboardState(history_len=120)
    for k, record in enumerate(recorded_stream()):
        state.update(record, now=100.0 + k)
    text = export(render(state, now=110.0))
    assert "1,111,104 / 5,000,000" in text  # frames of the last record, against the budget
    assert "100.0%" in text  # success on training goals, while exploring
    assert "50.0% ± 3.1" in text and "25.0%" in text  # greedy eval on train (with its error) and held-out goals
    # Greedy evaluation is the headline; the training success is labelled as exploring, below it.
    assert text.index("greedy, train") < text.index("exploring, train")
    assert "success (train)" not in text
    assert "GONE (dead)" in text and "1 dead" in text and "3 alive" in text
    assert "nodeB" in text and "4321" in text
    assert "open" in text and "81.2%" in text and "1,500" in text  # relabeler gate, accuracy, dataset
    for figure in ("200", "20.0%", "300", "30.0%", "400", "40.0%", "100", "10.0%"):
        assert figure in text  # replay composition: counts and shares
    assert "1,500/s" in text and "2.50/s" in text and "0.0123" in text and "43m13s" in text and "22%" in text
    assert "▂▃▃▄▅▆▆▇█" in text and "▃▄▅▅▆▇▇" in text  # exploring success and generator trends, 0-1 scale
    assert "greedy success" in text and "exploring success" in text
    assert "no telemetry" not in text and "waiting" not in text
    assert "greedy, averaged" not in text  # a run without dqn.average_tau has no such row


def test_failures_kept_out_behind_the_gate_get_a_row_only_when_there_are_some():
    state = DashboardState()
    state.update({**recorded_stream()[-1], "relabel_withheld": 1234}, now=0.0)
    text = export(render(state, now=0.5))
    assert "kept out (gate shut)" in text and "1,234" in text
    state = DashboardState()
    state.update({**recorded_stream()[-1], "relabel_withheld": 0}, now=0.0)
    assert "kept out" not in export(render(state, now=0.5))


def test_averaged_weights_get_their_own_row_and_summary_field():
    from higher_dist.launch.local_cluster import _summary

    record = {**recorded_stream()[-1], "success_rate_eval_train_averaged": 0.625,
              "success_rate_eval_train_averaged_se": 0.03}
    state = DashboardState()
    state.update(record, now=0.0)
    text = export(render(state, now=0.5))
    assert "greedy, averaged" in text and "62.5% ± 3.0" in text
    assert "averaged 0.62 |" in _summary(record) and "averaged" not in _summary(recorded_stream()[-1])


def test_the_share_of_greedy_episodes_that_cycled_shows_when_the_record_has_it():
    state = DashboardState()
    state.update({**recorded_stream()[-1], "cycling_rate_eval_train": 0.25}, now=0.0)
    assert figures(drawn_panels(export(render(state, now=0.5)))["Learning"])["greedy, cycling"] == "25.0%"
    state.update(recorded_stream()[-1], now=1.0)  # a run from before the share was measured: no row
    assert "greedy, cycling" not in figures(drawn_panels(export(render(state, now=1.5)))["Learning"])


def test_dead_role_row_is_red():
    state = DashboardState()
    state.update(recorded_stream()[-1], now=0.0)
    console = Console(record=True, width=140, file=io.StringIO(), force_terminal=True, color_system="truecolor")
    console.print(render(state, now=0.5))
    html = console.export_html(inline_styles=True)
    # Rich exports the standard "red" as #800000; the GONE cell is red and bold.
    assert 'color: #800000; text-decoration-color: #800000; font-weight: bold">GONE (dead)' in html


def test_a_records_figures_show_in_their_panels():
    record = {**recorded_stream()[-1], "frames": 123_456, "frames_budget": 1_000_000, "success_rate_train": 0.41,
              "rejected_messages": 15, "rejects_by_reason": {"mission_grammar": 12, "outcome": 3, "shape": 0}}
    state = DashboardState()
    state.update(record, now=0.0)
    drawn = drawn_panels(export(render(state, now=0.5)))
    assert figures(drawn["Learning"]) == {
        "frames": "123,456 / 1,000,000", "": "━━ 12%", "ETA": "9m44s",  # 876,544 frames left at 1,500/s
        "frames/s": "1,500/s", "updates": "9,000 (2.50/s)", "episodes": "450", "replay ratio": "8.00",
        "loss": "0.0123", "mean Q": "0.457", "epsilon": "0.100", "greedy, train": "50.0% ± 3.1",
        "greedy, held-out": "25.0%", "exploring, train": "41.0%"}
    assert figures(drawn["Relabeler"]) == {"dataset size": "1,500", "val. accuracy": "90.0%", "gate": "open",
                                           "relabels/s": "4.50/s", "relabelled eps": "90",
                                           "relabel accuracy": "81.2%"}
    assert figures(drawn["Replay"][:5]) == {"size": "1,000", "success": "200 20.0%", "wrong pick": "300 30.0%",
                                            "time-out": "400 40.0%", "relabelled": "100 10.0%"}
    assert drawn["Replay"][5].strip() == "█" * 30  # the stacked bar: 6 + 9 + 12 + 3 cells
    assert figures(drawn["Trends"]) == {"greedy success": "▅ 50.0%", "exploring success": "▄ 41.0%",
                                        "generator acc.": "▇ 90.0%"}
    # Roles sorted learner, relabeler, actors by id; then the rejects by reason, largest first, none of 0.
    assert role_rows(drawn["Cluster"]) == [
        ["learner", "0", "nodeA", "1000", "alive", "0.1 s", "-", "-", "0", "0"],
        ["relabeler", "0", "nodeA", "1001", "alive", "0.4 s", "-", "-", "0", "3"],
        ["actor", "0", "nodeA", "1002", "alive", "0.2 s", "812/s", "1", "0", "0"],
        ["actor", "1", "nodeB", "4321", "GONE (dead)", "31.0 s", "-", "7", "2", "0"],
        ["dropped: mission_grammar 12, outcome 3"]]
    assert drawn["Cluster.footer"] == ["rejected messages 15 · weights v42"]


@pytest.mark.parametrize("record, shown, roles", [
    ({}, {}, [["-"]]),
    ({"frames": None, "frames_budget": None, "roles": None, "relabel_gate_open": None}, {}, [["-"]]),
    ({"frames": 10, "frames_budget": 0, "frames_per_s": 0.0, "roles": [{"role": "actor"}, "junk"]},
     {("Learning", "frames"): "10 / 0", ("Learning", "frames/s"): "0.00/s"}, [["actor"] + ["-"] * 9]),
    ({"frames": "many", "loss": float("nan"), "replay_success": -1, "roles": [{"state": "dead", "id": "x"}]},
     {("Replay", "success"): "-1 -"}, [["-", "-", "-", "-", "GONE (dead)"] + ["-"] * 5]),
    ({"frames": 500, "success_rate_train": 0.25, "relabel_gate_open": False, "replay_timeout": 40},
     {("Learning", "frames"): "500 / -", ("Learning", "exploring, train"): "25.0%", ("Relabeler", "gate"): "closed",
      ("Replay", "time-out"): "40 100.0%", ("Trends", "exploring success"): "▃ 25.0%"}, [["-"]]),
])
def test_a_dash_stands_exactly_where_a_value_is_missing_or_unusable(record, shown, roles):
    state = DashboardState()
    state.update(record, now=0.0)
    drawn = drawn_panels(export(render(state, now=1.0)))
    for panel, nothing in NOTHING.items():
        rows = drawn[panel][:len(nothing)]  # the replay's bar, when drawn, comes after its rows
        expected = {label: shown.get((panel, label), dash) for label, dash in nothing.items()}
        assert figures(rows) == expected, panel
    assert role_rows(drawn["Cluster"]) == roles
    assert drawn["Cluster.footer"] == ["rejected messages - · weights v-"]


def test_waiting_and_stale_banners():
    state = DashboardState(stale_after_s=5.0, source="tcp://127.0.0.1:5558")
    assert "waiting for telemetry from tcp://127.0.0.1:5558" in export(render(state, now=0.0))
    state.update(recorded_stream()[-1], now=10.0)
    assert "no telemetry" not in export(render(state, now=14.0))
    text = export(render(state, now=22.4))
    assert "no telemetry for 12 s" in text and "1,111,104" in text  # last figures still shown


def test_histories_are_bounded():
    state = DashboardState(history_len=5)
    for k in range(50):
        state.update({"success_rate_train": k / 50, "generator_val_accuracy": None}, now=float(k))
    assert len(state.success_history) == 5 and len(state.generator_history) == 5
    state.update("not a dict")  # type: ignore[arg-type]
    assert state.garbage_frames == 1 and state.records_seen == 50


def test_the_dashboards_telemetry_endpoint_comes_from_the_learners_control_endpoint():
    # what `higher-dashboard --learner` connects to
    assert Endpoints.from_control("tcp://10.0.0.5:5555").telemetry == "tcp://10.0.0.5:5558"
    assert Endpoints.from_control("tcp://node-a:7000").telemetry == "tcp://node-a:7003"
    for bad in ("10.0.0.5:5555", "tcp://host", "tcp://host:notaport", "ipc:///tmp/x", "", "tcp://h:65534"):
        with pytest.raises(ValueError):
            Endpoints.from_control(bad)


def telemetry(record: dict) -> bytes:
    return bytes(encode("telemetry", {"record": record}, sender="learner")[0])


def test_decode_record():
    assert decode_record(telemetry({"frames": 3})) == {"frames": 3}
    assert decode_record(bytes(encode("stop")[0])) == STOP
    assert decode_record(b"\xc1garbage") is None
    assert decode_record(msgpack.packb({"frames": 3})) is None  # raw msgpack is not a telemetry message
    assert decode_record(bytes(encode("hello", {"role": "actor", "host": "h", "pid": 1, "protocol": 1})[0])) is None
    assert decode_record(b"") is None


def test_run_dashboard_over_a_real_socket():
    ctx = zmq.Context()
    pub = ctx.socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    port = pub.bind_to_random_port("tcp://127.0.0.1")
    endpoint = f"tcp://127.0.0.1:{port}"
    state = DashboardState()
    out = io.StringIO()
    result: dict = {}

    def dashboard() -> None:
        result["rc"] = run_dashboard(endpoint, refresh_per_s=20.0, stop_after_s=10.0,
                                     console=Console(file=out, width=140), state=state)

    thread = threading.Thread(target=dashboard, daemon=True)
    started = time.monotonic()
    thread.start()
    try:
        records = recorded_stream(4)
        # PUB drops everything until the subscription arrives (slow joiner): resend the first
        # record until the dashboard has seen it, then play the rest of the script once.
        while state.records_seen == 0 and time.monotonic() - started < 5:
            pub.send(telemetry(records[0]))
            time.sleep(0.05)
        assert state.records_seen > 0, "the dashboard never received a record"
        # Pauses longer than the dashboard's 50 ms poll: with CONFLATE only the newest frame waits.
        for frame in [telemetry(r) for r in records[1:]] + [b"\xc1\xc1 not msgpack"]:
            pub.send(frame)
            time.sleep(0.2)
        while thread.is_alive() and time.monotonic() - started < 8:
            pub.send(bytes(encode("stop")[0]))
            thread.join(0.1)
    finally:
        pub.close(0)
        ctx.term()
    assert not thread.is_alive() and result["rc"] == 0
    assert time.monotonic() - started < 8  # the stop record ended it, not stop_after_s
    assert state.record["frames"] == records[-1]["frames"]
    assert state.garbage_frames >= 1
    assert "370,368" in out.getvalue()  # the final render shows the last record's frames


def test_run_dashboard_stops_after_deadline_without_a_publisher():
    out = io.StringIO()
    started = time.monotonic()
    assert run_dashboard("tcp://127.0.0.1:1", refresh_per_s=20.0, stop_after_s=0.3, console=Console(file=out)) == 0
    assert time.monotonic() - started < 3
    assert "waiting for telemetry" in out.getvalue()


def test_the_cluster_panel_shows_rejects_by_reason():
    from higher_dist.roles.dashboard_view import reject_summary

    record = {"rejects_by_reason": {"mission_grammar": 12, "outcome": 3, "cell": 0}, "handler_errors": 1}
    assert reject_summary(record) == "dropped: mission_grammar 12, outcome 3; handler errors 1"
    assert reject_summary({"rejects_by_reason": {}}) == "" and reject_summary({}) == ""
    state = DashboardState()
    state.update({**record, "frames": 10, "rejected_messages": 15, "roles": []})
    out = io.StringIO()
    Console(file=out, width=140).print(render(state))
    assert "dropped: mission_grammar 12" in out.getvalue()


def test_the_hosts_layout_is_shown_under_the_header_when_the_learner_reports_it():
    from higher_dist.launch.layout import plan_layout

    layout = plan_layout(16).describe()
    state = DashboardState()
    state.update({**recorded_stream()[-1], "layout": layout}, now=0.0)
    assert f"layout  {layout}" in export(render(state, now=0.5))
    state.update(recorded_stream()[-1], now=1.0)  # a learner that reports none: no layout line
    assert "layout " not in export(render(state, now=1.5))


@pytest.mark.parametrize("width", [80, 100, 139, 140, 200])
def test_an_80_column_terminal_shows_frames_eta_and_the_role_table_uncut(width):
    state = DashboardState()
    records = recorded_stream()
    records[-1] = dict(records[-1], frames=12_345_678, frames_budget=100_000_000, frames_per_s=1500.0)
    for k, record in enumerate(records):
        state.update(record, now=100.0 + k)
    console = Console(record=True, width=width, file=io.StringIO(), color_system=None)
    console.print(render(state, now=110.0))
    text = console.export_text()
    assert max(len(line) for line in text.splitlines()) <= width
    assert "12,345,678 / 100,000,000" in text  # the frames count against its budget
    assert "ETA               16h13m56s" in text  # 87,654,322 frames to go at 1,500/s
    assert "…" not in text  # nothing cut: roles, hosts, pids and states are whole
    for cell in ("relabeler", "GONE (dead)", "4321", "nodeB", "812/s", "50.0% ± 3.1", "81.2%", "40.0%"):
        assert cell in text
