"""Issue 21's acceptance on a recording of ``--seconds`` (60) of ``vlp-agent sim``: every channel, its count
and rate, every message against its JSON schema, the ``mcap`` library's own reader, and the replays.

    python benchmarks/recording_check.py [--seconds 60] [--goal X,Y ...] [--fault SPEC ...] [--keep DIR]
                                         [--rate-tolerance 0.1] [--config FILE]

Runs ``vlp-agent sim --seconds S --json --record DIR/rec/run.mcap`` (by default with the goal the
whole-agent test sends, so that commands and goal statuses are recorded, and a 2 s laser fault half-way,
so that a device's health changes), then checks, each with its figures:

* ``channels`` (``agent.recording.check``): every channel present (those a run may leave empty: tags
  when no tag passed, goals when none was sent), each count equal to what the agent counted itself, and
  the periodic ones at their device's rate: scans at the world's laser rate, IMU samples at the IMU loop's,
  wheel states and commands at ``control.loop_rate_hz``, a VLP result (fix or no-fix) per camera frame
  and the camera frames at the world's frame rate; each rate measured over the time its device was up by
  the recording's own ``/health`` stamps, within ``--rate-tolerance`` (a ratio, 0.1: 0.9..1.1);
* ``mcap_reader``: each file opened with ``mcap.reader.make_reader`` (the MCAP library's indexed reader,
  not the project's), its summary's message count equal to the messages it iterates and to what
  ``agent.recording.reader`` read, the file closed whole;
* ``schemas``: every message validated against the JSON Schema its file embeds (the ``jsonschema``
  package: each schema first checked as a schema), ``foxglove.*`` schema names on the Foxglove channels;
* ``replay``: the fusion replayed from ``/fusion/input`` (every pose written reproduced; tolerance 0, the
  filter is deterministic given its inputs in their order and JSON keeps floats exactly), SLAM replayed
  from ``/laser/scan_raw`` and ``/slam/input`` (every live SLAM pose again, tolerance 0 likewise; see
  docs/recording.md, "Replay").

Prints one JSON object with every figure, ``pass`` and ``reasons`` (one line per failed check); exit
status 1 when one failed. Needs the test extras (``jsonschema``).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import jsonschema  # noqa: E402
from mcap.reader import make_reader  # noqa: E402

from agent.config import load_config  # noqa: E402
from agent.recording.check import Tolerance, check_channels, expected_rates  # noqa: E402
from agent.recording.messages import CHANNELS  # noqa: E402
from agent.recording.reader import Recording, read_recording  # noqa: E402
from agent.recording.slam_replay import replay_slam  # noqa: E402
from agent.runtime.imu_loop import IMU_PERIOD_S  # noqa: E402
from agent.runtime.recorder import replay_records  # noqa: E402
from agent.shipped import DEFAULT_SIM_CONFIG  # noqa: E402

FOXGLOVE = {"/laser/scan", "/pose", "/tf", "/map"}


def run_sim(args: argparse.Namespace, out: Path) -> tuple[dict[str, Any], list[str], float]:
    record = out / "rec" / "run.mcap"
    command = [sys.executable, "-m", "agent.cli", "sim", "--seconds", str(args.seconds), "--json"]
    command += ["--out", str(out), "--record", str(record)]
    if args.config:
        command += ["--config", str(args.config)]
    for goal in args.goal:
        command += ["--goal", goal]
    for fault in args.fault:
        command += ["--fault", fault]
    t0 = time.monotonic()
    done = subprocess.run(command, cwd=REPO, capture_output=True, text=True, check=False)
    wall_s = time.monotonic() - t0
    if done.returncode != 0:
        raise SystemExit(f"vlp-agent sim failed ({done.returncode}):\n{done.stderr[-3000:]}")
    summary: dict[str, Any] = json.loads(done.stdout)
    return summary, command, wall_s


def mcap_reader_check(recordings: list[Recording]) -> dict[str, Any]:
    """Each file through the mcap library's own (indexed, seeking) reader."""
    files = []
    ok = True
    for r in recordings:
        with open(r.path, "rb") as fp:
            reader = make_reader(fp)
            summary = reader.get_summary()
            iterated = sum(1 for _ in reader.iter_messages())
        stated = summary.statistics.message_count if summary and summary.statistics else None
        good = r.complete and stated == iterated == len(r.messages)
        ok &= good
        files.append(
            {
                "file": str(r.path),
                "summary_message_count": stated,
                "iterated": iterated,
                "project_reader": len(r.messages),
                "complete": r.complete,
                "ok": good,
            }
        )
    return {"files": files, "ok": ok}


def schema_check(recordings: list[Recording]) -> dict[str, Any]:
    validators: dict[tuple[str, str], Any] = {}
    invalid: list[str] = []
    wrong_names: list[str] = []
    checked = 0
    for r in recordings:
        for name, schema in r.schemas.items():
            cls = jsonschema.validators.validator_for(schema, default=jsonschema.Draft202012Validator)
            cls.check_schema(schema)
            validators[(str(r.path), name)] = cls(schema)
        for m in r.messages:
            checked += 1
            if m.schema_name != CHANNELS.get(m.topic):
                wrong_names.append(f"{m.topic}: {m.schema_name}")
            for error in validators[(str(r.path), m.schema_name)].iter_errors(m.data):
                if len(invalid) < 10:
                    invalid.append(f"{m.topic} at {m.log_time_ns}: {error.message}")
                else:
                    break
    foxglove = sorted({m.schema_name for r in recordings for m in r.messages if m.topic in FOXGLOVE})
    names_ok = not wrong_names and all(n.startswith("foxglove.") for n in foxglove)
    return {
        "validator": "jsonschema (each embedded schema checked as a schema first)",
        "messages": checked,
        "invalid": invalid,
        "foxglove_schemas": foxglove,
        "wrong_schema_names": sorted(set(wrong_names))[:10],
        "ok": not invalid and names_ok,
    }


def replay_check(recordings: list[Recording], summary: dict[str, Any]) -> dict[str, Any]:
    from agent.recording.reader import fusion_records

    records = list(fusion_records(recordings))
    fusion = replay_records(records)
    fusion_out = {
        "inputs": fusion.inputs,
        "poses_compared": fusion.outputs,
        "frames_out": summary.get("frames_out"),
        "max_pose_diff_m": fusion.max_position_difference_m,
        "max_yaw_diff_rad": fusion.max_yaw_difference_rad,
        "tolerance_m": 0.0,
    }
    fusion_ok = (
        fusion.outputs == summary.get("frames_out")
        and fusion.max_position_difference_m == 0.0
        and fusion.max_yaw_difference_rad == 0.0
    )
    slam = replay_slam(recordings)
    if isinstance(slam, str):
        slam_out: dict[str, Any] = {"error": slam}
        slam_ok = False
    else:
        recorded = sum(1 for r in recordings for m in r.messages if m.topic == "/slam/pose")
        slam_out = {
            "scans": slam.scans,
            "scans_missing": slam.scans_missing,
            "steps_differing": slam.steps_differing,
            "poses_recorded": recorded,
            "poses_compared": slam.poses_compared,
            "poses_unmatched": slam.poses_unmatched,
            "max_slam_diff_m": slam.max_diff_m,
            "max_slam_yaw_diff_rad": slam.max_yaw_diff_rad,
            "tolerance_m": 0.0,
        }
        slam_ok = (
            slam.scans_missing == 0
            and slam.steps_differing == 0
            and slam.poses_unmatched == 0
            and slam.poses_compared == recorded >= 1
            and slam.max_diff_m == 0.0
            and slam.max_yaw_diff_rad == 0.0
        )
    return {"fusion": {**fusion_out, "ok": fusion_ok}, "slam": {**slam_out, "ok": slam_ok}}


def check(args: argparse.Namespace, out: Path) -> dict[str, Any]:
    config = load_config(args.config or DEFAULT_SIM_CONFIG)
    assert config.sim is not None, "the check runs the simulated robot: a config with [sim]"
    world = config.sim.world
    rates = expected_rates(
        laser_hz=world.laser.scan_rpm / 60.0,
        camera_hz=world.camera.frame_rate_hz,
        imu_hz=1.0 / IMU_PERIOD_S,
        servo_hz=config.control.loop_rate_hz,
    )
    summary, command, wall_s = run_sim(args, out)
    recorded = summary.get("recording", {})
    recordings = [read_recording(Path(p)) for p in recorded.get("files", [])]
    messages = [m for r in recordings for m in r.messages]
    tolerance = Tolerance(1.0 - args.rate_tolerance, 1.0 + args.rate_tolerance, 1.0 - args.rate_tolerance / 2)
    channels = check_channels(messages, summary, rates, tolerance, config.recorder.map_period_s)
    reader = mcap_reader_check(recordings)
    schemas = schema_check(recordings)
    replay = replay_check(recordings, summary)
    reasons = list(channels["failures"])
    if recorded.get("record_dropped") or recorded.get("record_dropped_disk"):
        reasons.append(f"recording: {recorded.get('record_dropped')} samples dropped")
    if not reader["ok"]:
        reasons.append(f"mcap_reader: {[f for f in reader['files'] if not f['ok']]}")
    if not schemas["ok"]:
        reasons.append(f"schemas: {schemas['invalid'][:3] or schemas['wrong_schema_names']}")
    for part in ("fusion", "slam"):
        if not replay[part]["ok"]:
            reasons.append(f"replay {part}: {replay[part]}")
    size = sum(r.path.stat().st_size for r in recordings)
    return {
        "command": " ".join(command[2:]),
        "seconds": args.seconds,
        "run": {
            "seconds": summary.get("seconds"),
            "wall_s": round(wall_s, 1),
            "camera_frames": summary.get("camera_frames"),
            "frames_out": summary.get("frames_out"),
            "goals": summary.get("goals"),
            "latency_ms_p99": summary.get("latency_ms_p99"),
        },
        "recording": {
            "files": [str(r.path) for r in recordings],
            "messages": len(messages),
            "bytes": size,
            "mb_per_min": round(size / 1e6 / (channels["span_s"] / 60.0), 2) if channels["span_s"] else None,
            "dropped": recorded.get("record_dropped"),
            "chunks": recorded.get("record_chunks"),
            "chunks_late": recorded.get("record_chunks_late", 0),
            "close_lead_ms": recorded.get("record_close_lead_ms"),
            "writer_cpu_ms": recorded.get("record_writer_cpu_ms"),
        },
        "tolerance": {
            "rate": [tolerance.rate_low, tolerance.rate_high],
            "results_per_frame": tolerance.results_per_frame_low,
        },
        "span_s": channels["span_s"],
        "up_s": channels["up_s"],
        "channels": channels["channels"],
        "mcap_reader": reader,
        "schemas": schemas,
        "replay": replay,
        "pass": not reasons,
        "reasons": reasons,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="how long the sim runs (60)")
    parser.add_argument("--config", type=Path, default=None, help="a [sim] config (the shipped sim.toml)")
    parser.add_argument(
        "--goal", action="append", default=None, help="goals for the simulated controller (7.5,2.5)"
    )
    parser.add_argument(
        "--fault", action="append", default=None, help="faults to inject (laser@S+2, S: half-way)"
    )
    parser.add_argument("--no-goal", action="store_true", help="drive the world's route, send no goal")
    parser.add_argument("--no-fault", action="store_true", help="inject no fault")
    parser.add_argument(
        "--rate-tolerance", type=float, default=0.1, help="how far a rate may be off, as a ratio (0.1)"
    )
    parser.add_argument("--keep", type=Path, default=None, help="run in DIR and keep the files")
    args = parser.parse_args()
    args.goal = [] if args.no_goal else (args.goal or ["7.5,2.5"])
    args.fault = [] if args.no_fault else (args.fault or [f"laser@{args.seconds / 2:g}+2"])
    if args.keep is not None:
        args.keep.mkdir(parents=True, exist_ok=True)
        result = check(args, args.keep)
    else:
        with tempfile.TemporaryDirectory(prefix="recording-check-") as tmp:
            result = check(args, Path(tmp))
    print(json.dumps(result, indent=1))
    return 0 if result["pass"] else 1


if __name__ == "__main__":
    sys.exit(main())
