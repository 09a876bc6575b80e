"""Robustness benchmark: every wire codec against random and mutated input, with hypothesis.

For each codec, hypothesis draws inputs that are either random bytes or valid wire traffic (built by the
codec's own encoders and the fakes) mutated by byte flips, insertions, deletions, truncations, duplications
and splices. Each input is fed to a fresh streaming decoder whole and again in random chunks, and to the
codec's one-shot frame parser. The only exception allowed is the codec's own ``ProtocolError`` subclass,
and each input must finish within ``--hang-s`` seconds of CPU (a SIGPROF guard turns a hang into a failure;
CPU, not wall time, so that a machine busy with other work does not pass for a hanging decoder).

Prints one JSON object: per codec the number of inputs, messages decoded, errors raised, wall time and the
slowest input. Exit status 1 if any codec broke its contract.

    python benchmarks/fuzz_codecs.py                    # 100 000 inputs per codec
    python benchmarks/fuzz_codecs.py --examples 2000 --codec scip
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any

from hypothesis import HealthCheck, Phase, given, seed, settings
from hypothesis import strategies as st

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from firmware_protocol import command_frame, dynamixel, pose_frame, rfid, scip
from firmware_protocol.errors import ProtocolError


class Hang(Exception):
    """An input took longer than the hang bound."""


@dataclass
class Codec:
    name: str
    error: type[ProtocolError]
    make_decoder: Callable[[], Any]
    parse_frame: Callable[[bytes], Any] | None
    corpus: Callable[[], list[bytes]]


@dataclass
class Result:
    inputs: int = 0
    messages: int = 0
    frame_errors: int = 0
    slowest_ms: float = 0.0
    failures: list[str] = field(default_factory=list)


def scip_corpus() -> list[bytes]:
    from drivers.fakes.urg import FakeUrg

    fake = FakeUrg(seed=1)
    out = [
        fake.receive(cmd, 0.0)
        for cmd in (b"SCIP2.0\n", b"VV\n", b"PP\n", b"II\n", b"BM\n", b"GD0044072501\n", b"GS0044072502\n")
    ]
    out.append(fake.receive(b"MD0044072501003\n", 0.0) + fake.poll(0.2) + fake.poll(0.35))
    out.append(fake.receive(b"XX\n", 0.0) + fake.receive(b"GD0044099901\n", 0.0))
    return [b for b in out if b]


def dynamixel_corpus() -> list[bytes]:
    d = dynamixel
    return [
        d.encode_ping(1),
        d.encode_read(1, 132, 4),
        d.encode_write(1, 104, (200).to_bytes(4, "little")),
        d.encode_sync_read(128, 8, [1, 2]),
        d.encode_sync_write(104, 4, {1: b"\x96\x00\x00\x00", 2: b"\xaa\x00\x00\x00"}),
        d.encode_status(1, 0, bytes([0xA6, 0, 0, 0])),
        d.encode_status(2, 0x80, bytes([0xFF, 0xFF, 0xFD, 0x00])),
        d.encode_reboot(1) + d.encode_action(2),
    ]


def ascii_corpus(fmt: rfid.AsciiFormat) -> Callable[[], list[bytes]]:
    def build() -> list[bytes]:
        tags = (bytes.fromhex("7C0055F8C4"), bytes.fromhex("13005D1DA5"), bytes(5))
        return [rfid.encode_ascii_frame(t, fmt) for t in tags] + [
            b"".join(rfid.encode_ascii_frame(t, fmt) for t in tags)
        ]

    return build


def mercury_corpus() -> list[bytes]:
    return [
        rfid.encode_version_request(),
        rfid.encode_start_continuous_read(),
        rfid.encode_response(0x03, 0, bytes(range(20))),
        rfid.encode_response(0x22, 0x0400, b""),
        bytes.fromhex("FF0A2403E800000000000300EE589D"),
    ]


def pose_corpus() -> list[bytes]:
    pf = pose_frame
    frames = [
        pf.PoseFrame(1, 1_000_000, 1.5, -2.25, 0.5, 0.002, 0.01, pf.PoseFlags(0b1111)),
        pf.PoseFrame(2**32 - 1, 2**63, -100.0, 0.0, -3.14159, flags=pf.PoseFlags(0x0F00)),
        pf.PoseFrame(0, 0, 0.0, 0.0, 0.0),
    ]
    wires = [pf.encode_pose(f) for f in frames]
    return [*wires, b"".join(wires)]


def command_corpus() -> list[bytes]:
    cf = command_frame
    commands: list[cf.Command] = [
        cf.VelocityCommand(1, 0.3, -0.2, 0.5),
        cf.GoalCommand(2, 7, 3.5, -1.25, 1.0, 0.05, 0.05),
        cf.GoalCommand(3, 8, -12.0, 0.0, None, allow_unknown=True),
        cf.CancelCommand(4, 7),
        cf.StopCommand(5),
        cf.ResumeCommand(6),
    ]
    wires = [cf.encode_command(c) for c in commands]
    return [*wires, b"".join(wires)]


def goal_status_corpus() -> list[bytes]:
    cf = command_frame
    statuses = [
        cf.GoalStatus(1, 2, 7, cf.GoalState.ACCEPTED),
        cf.GoalStatus(2, cf.NO_SEQUENCE, 7, cf.GoalState.ACTIVE, remaining_m=3.2),
        cf.GoalStatus(3, 9, 8, cf.GoalState.REJECTED, cf.GoalReason.UNREACHABLE),
    ]
    wires = [cf.encode_goal_status(s) for s in statuses]
    pose = pose_frame.encode_pose(pose_frame.PoseFrame(1, 1000, 1.0, 2.0, 0.5))
    return [*wires, pose + b"".join(wires)]


CODECS: dict[str, Codec] = {
    "pose": Codec(
        "pose", pose_frame.PoseFrameError, pose_frame.PoseFrameDecoder, pose_frame.decode_pose, pose_corpus
    ),
    "command": Codec(
        "command",
        command_frame.CommandFrameError,
        command_frame.CommandDecoder,
        command_frame.decode_command,
        command_corpus,
    ),
    "goal-status": Codec(
        "goal-status",
        command_frame.CommandFrameError,
        command_frame.GoalStatusDecoder,
        command_frame.decode_goal_status,
        goal_status_corpus,
    ),
    "scip": Codec("scip", scip.ScipError, scip.ScipDecoder, scip.parse_reply, scip_corpus),
    "dynamixel": Codec(
        "dynamixel",
        dynamixel.DynamixelError,
        dynamixel.DynamixelDecoder,
        dynamixel.decode_packet,
        dynamixel_corpus,
    ),
    "rfid-id12la": Codec(
        "rfid-id12la",
        rfid.RfidError,
        lambda: rfid.AsciiFrameDecoder(rfid.AsciiFormat.ID12LA),
        lambda b: rfid.decode_ascii_frame(b, rfid.AsciiFormat.ID12LA),
        ascii_corpus(rfid.AsciiFormat.ID12LA),
    ),
    "rfid-rdm6300": Codec(
        "rfid-rdm6300",
        rfid.RfidError,
        lambda: rfid.AsciiFrameDecoder(rfid.AsciiFormat.RDM6300),
        lambda b: rfid.decode_ascii_frame(b, rfid.AsciiFormat.RDM6300),
        ascii_corpus(rfid.AsciiFormat.RDM6300),
    ),
    "rfid-mercury": Codec(
        "rfid-mercury",
        rfid.RfidError,
        rfid.MercuryResponseDecoder,
        rfid.decode_response_frame,
        mercury_corpus,
    ),
}


def mutations(corpus: Sequence[bytes]) -> st.SearchStrategy[bytes]:
    """Valid traffic, then a few edits: flip, insert, delete, truncate, duplicate, splice."""

    @st.composite
    def mutate(draw: st.DrawFn) -> bytes:
        data = bytearray(draw(st.sampled_from(corpus)))
        for _ in range(draw(st.integers(0, 6))):
            op = draw(st.sampled_from(["flip", "insert", "delete", "truncate", "duplicate", "splice"]))
            pos = draw(st.integers(0, len(data)))
            if op == "flip" and data:
                i = min(pos, len(data) - 1)
                data[i] = draw(st.integers(0, 255))
            elif op == "insert":
                data[pos:pos] = draw(st.binary(min_size=1, max_size=8))
            elif op == "delete":
                del data[pos : pos + draw(st.integers(1, 16))]
            elif op == "truncate":
                del data[pos:]
            elif op == "duplicate":
                data[pos:pos] = data[pos : pos + draw(st.integers(1, 64))]
            elif op == "splice":
                other = draw(st.sampled_from(corpus))
                data[pos:pos] = other[: draw(st.integers(0, len(other)))]
        return bytes(data)

    return mutate()


def check(codec: Codec, data: bytes, cuts: list[int], result: Result) -> None:
    """Feed ``data`` whole and in chunks to fresh decoders, and to the frame parser: only codec errors."""
    started = time.perf_counter()
    whole = codec.make_decoder().feed(data)
    chunked_decoder = codec.make_decoder()
    chunked: list[Any] = []
    last = 0
    for cut in [*sorted({c % (len(data) + 1) for c in cuts}), len(data)]:
        chunked.extend(chunked_decoder.feed(data[last:cut]))
        last = cut
    if len(whole) != len(chunked):
        # Chunking may only delay a decision, never change what is decoded from a complete stream.
        result.failures.append(
            f"chunking changed the result: {len(whole)} vs {len(chunked)} on {data[:64].hex()}"
        )
    result.messages += len(whole)
    if codec.parse_frame is not None:
        try:
            codec.parse_frame(data)
        except codec.error:
            result.frame_errors += 1
    result.slowest_ms = max(result.slowest_ms, 1000 * (time.perf_counter() - started))


def fuzz_codec(codec: Codec, examples: int, hang_s: float, seed_value: int) -> tuple[Result, float]:
    result = Result()
    corpus = codec.corpus()
    strategy = st.one_of(st.binary(max_size=4096), mutations(corpus))

    hung: list[bool] = []

    def on_alarm(signum: int, frame: FrameType | None) -> None:
        # Remembered as well as raised: an alarm that lands in a gc callback (Hypothesis times them) has its
        # exception swallowed by the interpreter ("Exception ignored in gc callback"), and the input would
        # then pass as fine.
        hung.append(True)
        raise Hang(f"{codec.name}: one input took more than {hang_s} s of CPU")

    previous = signal.signal(signal.SIGPROF, on_alarm)

    @seed(seed_value)
    @settings(
        max_examples=examples,
        deadline=None,
        database=None,
        derandomize=False,
        suppress_health_check=list(HealthCheck),
        # No shrinking: a codec's failures are collected, not raised; what is raised (a hang, a streaming
        # decoder's error) ends the codec's run, and shrinking it would replay the hang hundreds of times.
        phases=[Phase.explicit, Phase.reuse, Phase.generate],
    )
    @given(strategy, st.lists(st.integers(0, 1 << 16), max_size=8))
    def run(data: bytes, cuts: list[int]) -> None:
        result.inputs += 1
        signal.setitimer(signal.ITIMER_PROF, hang_s)
        try:
            check(codec, data, cuts, result)
            if hung:
                raise Hang(f"{codec.name}: one input took more than {hang_s} s of CPU (in a gc callback)")
        except (Hang, codec.error):
            raise
        except Exception as exc:  # the contract: nothing but the codec's own error, ever
            result.failures.append(f"{type(exc).__name__}: {exc} on {data[:64].hex()}")
        finally:
            signal.setitimer(signal.ITIMER_PROF, 0)

    started = time.perf_counter()
    try:
        run()
    except Hang as exc:
        result.failures.append(str(exc))
    except codec.error as exc:
        # A streaming decoder must absorb bad input; only one-shot parsers may raise.
        result.failures.append(f"streaming decoder raised {exc!r}")
    finally:
        signal.signal(signal.SIGPROF, previous)
    return result, time.perf_counter() - started


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--examples", type=int, default=100_000, help="inputs per codec (default 100000)")
    parser.add_argument("--codec", choices=sorted(CODECS), action="append", help="only these codecs")
    parser.add_argument("--hang-s", type=float, default=2.0, help="one input's CPU bound (default 2 s)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    report: dict[str, Any] = {"examples_requested": args.examples, "codecs": {}}
    ok = True
    for name in args.codec or sorted(CODECS):
        result, wall_s = fuzz_codec(CODECS[name], args.examples, args.hang_s, args.seed)
        ok &= not result.failures
        report["codecs"][name] = {
            "inputs": result.inputs,
            "messages_decoded": result.messages,
            "frame_errors": result.frame_errors,
            "wall_s": round(wall_s, 2),
            "inputs_per_s": round(result.inputs / wall_s) if wall_s else None,
            "slowest_input_ms": round(result.slowest_ms, 2),
            "failures": result.failures[:10],
        }
        print(
            f"{name}: {result.inputs} inputs in {wall_s:.1f} s, {len(result.failures)} failures",
            file=sys.stderr,
            flush=True,
        )
    report["ok"] = ok
    print(json.dumps(report, indent=2))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
