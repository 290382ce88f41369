"""Entry points. Each parses its flags, builds the config, and hands over to one module; bad flags and
bad config values are refused with a message that says what is wrong (exit code 2). Each command imports
the module it hands over to only when it runs, so no command pays for another's imports (torch, zmq, rich)."""
from __future__ import annotations

import argparse
import json
import signal
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Callable

from higher_dist.config import ConfigError, from_dict
from higher_dist.launch.memory import bound_arenas, trace_from_env
from higher_dist.launch.parent import follow_launcher
from higher_dist.config_flags import (DefaultsHelp, add_config_flags, config_from_args, non_negative_int,
                                     positive_int, resumed_config)


def _die(prog: str, message: str) -> int:
    print(f"{prog}: error: {message}", file=sys.stderr)
    return 2


def _network_flags(p: argparse.ArgumentParser) -> None:
    p.add_argument("--host", default="127.0.0.1", help="address the learner advertises (loopback by default)")
    p.add_argument("--bind-host", default=None, help="interface to bind, e.g. 0.0.0.0 across hosts")
    p.add_argument("--port-base", type=int, default=None, help="first of the five ports (default: 5555)")
    _security_flags(p, binds=True)


def _security_flags(p: argparse.ArgumentParser, binds: bool, connects: bool = False) -> None:
    p.add_argument("--keys", default=None, metavar="DIR",
                   help="CURVE keys folder (from higher-keys): encrypt every socket, admit only listed clients")
    if connects:
        p.add_argument("--key", default=None, metavar="NAME",
                       help="the client pair NAME.key_secret in --keys to connect with (default: the pair named "
                            "after the role, else 'client', else the folder's only pair; a dashboard: any pair)")
    if binds:
        p.add_argument("--insecure", action="store_true",
                       help="allow binding beyond loopback without --keys (anyone reaching the ports joins the run)")


def _security(args: argparse.Namespace, role: str = "client"):
    """The Security of a role's flags; a --keys folder that is not there is refused by name, and so is
    a client key pair that cannot be chosen (several, none named after the role: --key)."""
    from higher_dist.wire.security import Security

    if args.keys is not None and not Path(args.keys).is_dir():
        raise ConfigError(f"--keys {args.keys}: no such folder (make one with higher-keys)")
    security = Security(args.keys, insecure=getattr(args, "insecure", False), client_name=getattr(args, "key", None),
                        role=role)
    if args.keys is not None and role != "client":
        security.client()  # the pair it would use exists and is unambiguous, or a one-line refusal now
    return security


def _run(prog: str, build: Callable[[], int]) -> int:
    follow_launcher()  # a role started by higher-cluster ends when the launcher does
    bound_arenas()  # before torch and ZeroMQ start threads: see launch/memory.py
    trace_from_env(prog)  # only when HIGHER_MEMTRACE_DIR is set (higher-bench soak --trace-memory)
    try:
        return build()
    except ValueError as e:  # a ConfigError (a ValueError too) or other bad input, e.g. a malformed endpoint
        return _die(prog, str(e))


def _world_checked(cfg):
    """The config, once its world can be built (a BabyAI id of a pickup, go-to or open level): refused
    here in one line rather than by every role that would build it and die."""
    from higher_dist.world.spec import WorldSpec  # numpy only; minigrid only for a BabyAI world

    WorldSpec.of(cfg.world)
    return cfg


def cluster_main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser("higher-cluster", description="Run learner, relabeler, actors and dashboard here.",
                                formatter_class=DefaultsHelp)
    add_config_flags(p, layout_actors=True)
    _network_flags(p)
    p.add_argument("--run-dir", default=None, help="where config, metrics and checkpoints go (default: runs/PRESET-WORLD-sSEED-TIME)")
    p.add_argument("--resume", action="store_true", help="continue from the run directory's checkpoints")
    p.add_argument("--no-dashboard", action="store_true", help="no live dashboard (prints a line per interval)")
    p.add_argument("--max-restarts", type=non_negative_int, default=5,
                   help="restarts of one role before giving up (default: 5)")
    args = p.parse_args(argv)

    def go() -> int:
        from higher_dist.launch.layout import available_cores, default_actors
        from higher_dist.launch.local_cluster import run_local_cluster
        from higher_dist.learning.devices import resolve_device

        if args.resume and not args.run_dir:
            raise ConfigError("--resume: name the run to continue with --run-dir")
        if args.resume:
            cfg = resumed_config(args, args.run_dir)  # the run's config.json; changed flags refused by name
        else:
            cfg = _world_checked(config_from_args(args))
            if args.actors is None:  # the layout's choice for this host and the learner's device
                cfg = replace(cfg, actors=default_actors(available_cores(), str(resolve_device(cfg.device))))
        if args.print_config:
            print(cfg.to_json())
            return 0
        run_dir = args.run_dir or time.strftime(f"runs/{cfg.preset}-{cfg.world.name}-s{cfg.seed}-%Y%m%d-%H%M%S")
        if not args.resume and (Path(run_dir) / "learner.ckpt").exists():
            raise ConfigError(f"--run-dir {run_dir} already holds a run: add --resume to continue it, "
                              "or choose another --run-dir")
        return run_local_cluster(cfg, run_dir, resume=args.resume, dashboard=not args.no_dashboard,
                                 host=args.host, port_base=args.port_base, max_restarts=args.max_restarts,
                                 security=_security(args), bind_host=args.bind_host)

    return _run("higher-cluster", go)


def learner_main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser("higher-learner", description="The learner: replay, DQN, weights, the run's config.",
                                formatter_class=DefaultsHelp)
    add_config_flags(p)
    _network_flags(p)
    p.add_argument("--config", default=None, help="a config.json to run instead of --preset/--world/--set")
    p.add_argument("--run-dir", required=True)
    p.add_argument("--resume", action="store_true")
    p.add_argument("--layout", default=None, help=argparse.SUPPRESS)  # higher-cluster's host layout, for the dashboard
    args = p.parse_args(argv)

    def go() -> int:
        from higher_dist.launch.topology import DEFAULT_BASE_PORT, Endpoints
        from higher_dist.roles.learner import run_learner

        if args.config:
            try:
                data = json.loads(open(args.config).read())
            except (OSError, json.JSONDecodeError) as e:
                raise ConfigError(f"--config {args.config}: cannot read it ({e})") from None
            cfg = from_dict(data)
        elif args.resume:
            cfg = resumed_config(args, args.run_dir)
        else:
            cfg = _world_checked(config_from_args(args))
        if args.print_config:
            print(cfg.to_json())
            return 0
        endpoints = Endpoints.from_base(args.host, args.port_base or DEFAULT_BASE_PORT)
        return run_learner(cfg, endpoints, args.run_dir, resume=args.resume, bind_host=args.bind_host,
                           security=_security(args), threads=args.threads, layout=args.layout)

    return _run("higher-learner", go)


def _role_flags(p: argparse.ArgumentParser, binds: bool = False) -> None:
    p.add_argument("--learner", required=True, help="the learner's control endpoint, tcp://HOST:PORT")
    _security_flags(p, binds=binds, connects=True)
    p.add_argument("--threads", type=positive_int, default=1,
                   help="torch threads (the run's torch_threads is the learner's share)")


def relabeler_main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser("higher-relabeler", description="The relabeler: instruction generator service.",
                                formatter_class=DefaultsHelp)
    _role_flags(p, binds=True)
    p.add_argument("--bind-host", default=None, help="interface to bind its episodes socket")
    p.add_argument("--advertise", default=None, metavar="tcp://HOST:PORT",
                   help="its episodes endpoint as actors should reach it (default: the learner's host, base+4)")
    p.add_argument("--state-dir", default=None, help="where its checkpoint goes (default: runs/relabeler)")
    p.add_argument("--resume", action="store_true")
    args = p.parse_args(argv)

    def go() -> int:
        from higher_dist.roles.relabeler import run_relabeler

        if args.advertise:
            from higher_dist.launch.topology import parse_endpoint

            parse_endpoint(args.advertise)
        return run_relabeler(args.learner, state_dir=args.state_dir, resume=args.resume, bind_host=args.bind_host,
                             security=_security(args, "relabeler"), threads=args.threads,
                             advertise=args.advertise)

    return _run("higher-relabeler", go)


def actor_main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser("higher-actor", description="An actor: B environments, epsilon-greedy.",
                                formatter_class=DefaultsHelp)
    _role_flags(p)
    p.add_argument("--actor-id", type=non_negative_int, default=None,
                   help="fixed index (sets its epsilon) (default: the learner assigns one)")
    args = p.parse_args(argv)

    def go() -> int:
        from higher_dist.roles.actor import run_actor

        return run_actor(args.learner, actor_id=args.actor_id, security=_security(args, "actor"),
                         threads=args.threads)

    return _run("higher-actor", go)


def dashboard_main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser("higher-dashboard", description="Attach a live dashboard to a running cluster.",
                                formatter_class=DefaultsHelp)
    p.add_argument("--learner", required=True, help="the learner's control endpoint, tcp://HOST:PORT")
    p.add_argument("--seconds", type=float, default=None, help="exit after this long")
    _security_flags(p, binds=False, connects=True)
    args = p.parse_args(argv)

    def go() -> int:
        from higher_dist.launch.topology import Endpoints
        from higher_dist.roles.dashboard import run_dashboard

        return run_dashboard(Endpoints.from_control(args.learner).telemetry, stop_after_s=args.seconds,
                             security=_security(args, "dashboard"))

    return _run("higher-dashboard", go)


def run_main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser("higher-run", description="All components in one process (debugging, tests).",
                                formatter_class=DefaultsHelp)
    add_config_flags(p)
    p.add_argument("--run-dir", required=True)
    p.add_argument("--metrics-every", type=positive_int, default=10_000, help="frames between metric lines")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --run-dir from its runner.ckpt, with its config.json")
    args = p.parse_args(argv)

    def go() -> int:
        import torch

        from higher_dist.learning.runner import SingleProcessRunner
        from higher_dist.rundir import RunDir

        from higher_dist.launch.layout import available_cores

        if args.resume:
            cfg = resumed_config(args, args.run_dir)  # the run's config.json; changed flags refused by name
            state = RunDir(args.run_dir).load_checkpoint("runner")
            if state is None:
                raise ConfigError(f"--resume: {args.run_dir} holds no runner.ckpt to continue from (a run of "
                                  "higher-cluster resumes with higher-cluster --resume)")
        else:
            cfg = _world_checked(config_from_args(args))
            state = None
        if args.print_config:
            print(cfg.to_json())
            return 0
        held = [name for name in ("config.json", "metrics.jsonl") if (Path(args.run_dir) / name).exists()]
        if held and not args.resume:
            raise ConfigError(f"--run-dir {args.run_dir} already holds a run ({', '.join(held)}): add --resume "
                              "to continue it, or choose another --run-dir")
        # One process acts and learns: it may use every core.
        torch.set_num_threads(cfg.torch_threads or available_cores())
        rd = RunDir(args.run_dir, tensorboard=cfg.tensorboard)
        rd.write_config(cfg)

        def log(record: dict) -> None:
            rd.append_metrics(record)
            print(json.dumps(record), flush=True)

        runner = SingleProcessRunner(cfg, log=log)
        if state is not None:
            runner.load_state_dict(state)
            print(f"higher-run: resumed {args.run_dir} at {runner.frames_done:,} frames", flush=True)
        stopping = []  # Ctrl-C or SIGTERM: finish the round, checkpoint, exit
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stopping.append(True))
        runner.run(metrics_every=args.metrics_every, checkpoint=lambda: rd.save_checkpoint("runner", runner.state_dict()),
                   checkpoint_every_s=cfg.checkpoint_every_s, stop=lambda: bool(stopping))
        return 0

    return _run("higher-run", go)


def bench_main(argv: list[str] | None = None) -> int:
    from higher_dist.bench import main

    return main(sys.argv[1:] if argv is None else argv)


def plot_main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) == 1 and (Path(argv[0]) / "plan.json").is_file():
        # A higher-reproduce folder: the paper's figures (mean and one std over seeds) and results.md.
        from higher_dist.reproduce.cli import report

        return report(Path(argv[0]))
    from higher_dist.plot import main

    return main(argv)


def reproduce_main(argv: list[str] | None = None) -> int:
    from higher_dist.reproduce.cli import main

    return main(sys.argv[1:] if argv is None else argv)


def render_main(argv: list[str] | None = None) -> int:
    from higher_dist.render import main

    return main(sys.argv[1:] if argv is None else argv)


def keys_main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser("higher-keys", description="Make CURVE key pairs for a multi-host cluster.",
                                formatter_class=DefaultsHelp)
    p.add_argument("dir", help="folder to write server and client keys into")
    p.add_argument("--client", default=None, metavar="NAME",
                   help="make the key pair of one host or role, NAME.key(_secret), listed in allowed_clients/ "
                        "with --role (default: one 'client' pair shared by every host, which may take any role)")
    p.add_argument("--role", default=None, metavar="ROLES",
                   help="what --client's key may be: actor, relabeler, a comma-separated list, or any "
                        "(required with --client)")
    args = p.parse_args(argv)
    from higher_dist.wire.allowlist import parse_roles
    from higher_dist.wire.security import generate_keys

    try:
        if (args.client is None) != (args.role is None):
            raise ValueError("--client NAME and --role ROLES go together (or neither: the shared 'client' pair)")
        roles = parse_roles(args.role) if args.role is not None else None
        made = generate_keys(args.dir, clients=(args.client or "client",), roles=roles)
    except ValueError as e:
        return _die("higher-keys", str(e))
    name = args.client or "client"
    print(f"keys written to {args.dir}: {made[name]}, its secret {name}.key_secret and its allow-list entry "
          f"(roles: {args.role or 'any'}); copy server.key and this pair to the host that runs it")
    return 0
