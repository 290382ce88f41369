"""Wire benchmark: codec cost per episode batch, and episodes/s through PUSH/PULL between two processes.

    python -m higher_dist.bench.wire_bench [--episodes 32] [--steps 40] [--seconds 3]

Prints a table, then one JSON object on the last line (for scripts and the results folder).
The producer runs in a separate process (spawn), as an actor would; the consumer does what the relabeler
does on receipt: decode (which validates every value) and unpack into Episodes.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing
import time
from typing import Callable

import numpy as np
import zmq

from dataclasses import replace

from higher_dist.config import WorldConfig
from higher_dist.learning.episode import Episode
from higher_dist.learning.random_episodes import real_episodes
from higher_dist.world.spec import WorldSpec
from higher_dist.wire import (RejectCounter, bind_random, decode, decode_weights, encode, encode_weights,
                              make_socket, pack_episodes, recv_message, send, unpack_episodes)



def random_episodes(n: int, max_steps: int, seed: int = 0) -> list[Episode]:
    """Real episodes of a random policy on the paper world with this episode limit (the wire checks
    episodes against the world, so made-up arrays would be refused)."""
    return real_episodes(_world(max_steps), n, seed=seed)


def _world(max_steps: int) -> WorldConfig:
    return replace(WorldConfig(), max_steps=max_steps)


def _time_ms(fn: Callable[[], object], min_seconds: float = 0.3, min_repeats: int = 20) -> float:
    """Mean milliseconds per call, repeating for at least min_seconds (and min_repeats calls)."""
    fn()  # warm caches and lazy imports
    count, start = 0, time.perf_counter()
    while count < min_repeats or time.perf_counter() - start < min_seconds:
        fn()
        count += 1
    return (time.perf_counter() - start) / count * 1e3


def _producer(endpoint: str, n: int, max_steps: int, seconds: float, seed: int) -> None:
    """Child process: pack + encode + send batches as fast as the consumer takes them, then `stop`."""
    episodes = random_episodes(n, max_steps, seed)
    ctx = zmq.Context()
    push = make_socket(ctx, zmq.PUSH, connect=endpoint, linger_ms=2000)
    seq, deadline = 0, time.monotonic() + seconds
    while time.monotonic() < deadline:
        send(push, encode("episodes", *pack_episodes(episodes), sender="bench", seq=seq))
        seq += 1
    send(push, encode("stop", {"reason": "done"}, sender="bench", seq=seq))
    push.close()
    ctx.term()


def push_pull_throughput(n: int, max_steps: int, seconds: float) -> dict[str, float]:
    ctx = zmq.Context()
    pull = make_socket(ctx, zmq.PULL)
    endpoint = bind_random(pull)
    child = multiprocessing.get_context("spawn").Process(target=_producer, args=(endpoint, n, max_steps,
                                                                               seconds, 1), daemon=True)
    child.start()
    counter = RejectCounter()
    episodes = batches = payload = 0
    start = end = None
    try:
        # Generous timeout for the first message: a spawned child imports numpy and zmq first.
        while True:
            msg = recv_message(pull, 30_000 if start is None else 5_000, counter)
            if msg is None:
                raise RuntimeError(f"producer went silent (alive={child.is_alive()}, rejects={counter.counts()})")
            if msg.type == "stop":
                end = time.perf_counter()
                break
            if start is None:
                start = time.perf_counter()  # count from the first batch, not from process start-up
                continue
            episodes += len(unpack_episodes(msg, WorldSpec.of(_world(max_steps))))
            payload += sum(arr.nbytes for arr in msg.arrays.values())
            batches += 1
    finally:
        child.join(timeout=10)
        if child.is_alive():
            child.terminate()
            child.join()
        pull.close(linger=0)
        ctx.term()
    elapsed = max(end - start, 1e-9)
    return {"episodes_per_s": episodes / elapsed, "batches_per_s": batches / elapsed,
            "mib_per_s": payload / elapsed / 2 ** 20, "seconds": elapsed, "rejects": counter.total}


def main(argv: list[str] | None = None) -> int:
    """Entry point of `higher-bench wire`: prints the table and the JSON line, returns the exit status."""
    run(argv)
    return 0


def run(argv: list[str] | None = None) -> dict[str, float]:
    """The benchmark itself; returns the summary that is printed as the last line."""
    parser = argparse.ArgumentParser(prog="higher-bench wire", description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=32, help="episodes per batch")
    parser.add_argument("--steps", type=int, default=40, help="max steps per episode (time-outs use all)")
    parser.add_argument("--seconds", type=float, default=3.0, help="duration of the PUSH/PULL run")
    parser.add_argument("--weights", type=int, default=300_000, help="float32 parameters in the weights test")
    args = parser.parse_args(argv)

    episodes = random_episodes(args.episodes, args.steps)
    fields, arrays = pack_episodes(episodes)
    frames = [bytes(f) for f in encode("episodes", fields, arrays)]
    message = decode(frames)
    batch_bytes = sum(len(f) for f in frames)
    rng = np.random.default_rng(0)
    sizes = [args.weights // 2, args.weights // 4, args.weights - args.weights // 2 - args.weights // 4]
    weights = {f"layer{i}.weight": rng.standard_normal(size).astype(np.float32) for i, size in enumerate(sizes)}
    weights_frame = encode_weights(1, weights)

    results = {
        "pack_ms": _time_ms(lambda: pack_episodes(episodes)),
        "encode_ms": _time_ms(lambda: encode("episodes", fields, arrays)),
        "decode_ms": _time_ms(lambda: decode(frames)),
        "unpack_ms": _time_ms(lambda: unpack_episodes(message, WorldSpec.of(_world(args.steps)))),
        "weights_encode_ms": _time_ms(lambda: encode_weights(1, weights)),
        "weights_decode_ms": _time_ms(lambda: decode_weights(weights_frame)),
    }
    per_batch = results["pack_ms"] + results["encode_ms"] + results["decode_ms"] + results["unpack_ms"]
    results["codec_episodes_per_s"] = args.episodes / per_batch * 1e3
    through = push_pull_throughput(args.episodes, args.steps, args.seconds)

    steps_in_batch = int(message.arrays["actions"].shape[0])
    print(f"wire benchmark: batches of {args.episodes} episodes ({steps_in_batch} steps, "
          f"{batch_bytes / 1024:.0f} KiB on the wire)")
    print(f"{'stage':<34}{'ms/batch':>10}")
    for key, label in (("pack_ms", "pack_episodes"), ("encode_ms", "encode (header + zero-copy frames)"),
                       ("decode_ms", "decode + validate"), ("unpack_ms", "unpack_episodes (checks, copies)")):
        print(f"{label:<34}{results[key]:>10.3f}")
    print(f"{'codec round trip':<34}{per_batch:>10.3f}   ({results['codec_episodes_per_s']:,.0f} episodes/s, one core)")
    print(f"weights, {args.weights:,} float32 ({len(weights_frame) / 2 ** 20:.1f} MiB, one frame): "
          f"encode {results['weights_encode_ms']:.2f} ms, decode {results['weights_decode_ms']:.2f} ms")
    print(f"PUSH/PULL tcp loopback, 2 processes, {through['seconds']:.1f} s: "
          f"{through['episodes_per_s']:,.0f} episodes/s, {through['batches_per_s']:,.0f} batches/s, "
          f"{through['mib_per_s']:.1f} MiB/s, {through['rejects']} rejected")
    summary = {"bench": "wire", "episodes_per_batch": args.episodes, "steps_per_batch": steps_in_batch,
               "batch_bytes": batch_bytes, **{k: round(v, 4) for k, v in results.items()},
               "pushpull_episodes_per_s": round(through["episodes_per_s"], 1),
               "pushpull_batches_per_s": round(through["batches_per_s"], 2),
               "pushpull_mib_per_s": round(through["mib_per_s"], 2), "rejects": through["rejects"]}
    print(json.dumps(summary))
    return summary


if __name__ == "__main__":
    raise SystemExit(main())
