"""``kill -9`` at random instants of a mapping run: is the last saved map whole, and how much was lost?

    python benchmarks/map_kill.py [--instants 20] [--mid-save 5] [--interval 1.0] [--span 4.0] [--seed 0]
                                  [--no-record]

Each instant is a fresh ``vlp-agent sim`` (the office route, VLP + SLAM, ``[slam] save_interval_s =
INTERVAL``) in a session of its own, SIGKILLed as a whole (the agent, its SLAM process and its camera
renderer, as a power cut would) at a random moment ``U(0, SPAN)`` s after its first periodic save is on
disk. A save lasts tens of milliseconds a second, so random instants seldom land inside one: the last
``--mid-save`` instants instead wait ``U(0, SPAN)`` s and then kill at the first sign of a save under way
(a new image or a temporary file in the folder, polled every millisecond), between the image's write and
the YAML's rename. Then, per instant:

* ``loads``: ``map.yaml`` and the image it names load whole (``agent.slam.mapio.load_map``), and so does
  ``map.prev.yaml`` when there is one;
* ``age_s``: the kill time minus the *content time* of that map (when the SLAM loop took it out of the
  mapper: every scan mapped by then is in it; the saver writes it into the image's header,
  ``content_monotonic_ns``, both on ``CLOCK_MONOTONIC``): the mapping lost. The saver starts each save
  its measured lead early so that this stays within one interval at every instant
  (``agent.runtime.map_saver``); ``commit_age_s`` is the kill time minus the YAML's mtime (the commit);
* ``left_over``: temporary files and unnamed images the kill left (never ``map.yaml`` itself: that is
  only ever a rename), and whether ``tidy_map_folder`` (what the next start runs) removes every one while
  the map still loads.
* ``mcap_lost_s``: the runs also flight-record (``--record``, ``[recorder] chunk_s`` 1 s; not with
  ``--no-record``): the kill time minus the log time of the newest message the recording still reads
  (``agent.recording.reader``: whole chunks only), both on ``CLOCK_MONOTONIC``; with ``mcap_messages``
  and ``mcap_files_cut`` (files that read only up to a cut, at most the last one).

Prints one JSON object: the per-instant records and ``all_loaded``, ``max_age_s``, ``max_left_over`` and
``max_mcap_lost_s``; and the verdict: ``checks`` (each bound with its figure and whether it held: every map
loads and nothing left over survives the tidy; ``max_age_s`` <= the interval; ``max_mcap_lost_s`` <= the
recorder's ``chunk_s``), ``pass`` and ``reasons`` (the checks that failed). Exit status 1 when one failed.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from agent.config import RecorderConfig  # noqa: E402
from agent.recording.reader import read_recording, recording_files  # noqa: E402
from agent.runtime.map_saver import content_stamp_ns  # noqa: E402
from agent.slam.mapio import load_map, tidy_map_folder  # noqa: E402
from drivers.errors import ConfigError  # noqa: E402

EXAMPLES = REPO / "agent" / "examples"
_FIRST_SAVE_TIMEOUT_S = 120.0


def mapping_config(folder: Path, interval_s: float) -> Path:
    """The simulated robot's example config, mapping, saving every ``interval_s``."""
    text = (EXAMPLES / "sim.toml").read_text(encoding="utf-8")
    text = text.replace('"worlds/office.toml"', f'"{EXAMPLES / "worlds" / "office.toml"}"')
    text = text.replace("[slam]\n", f"[slam]\nsave_interval_s = {interval_s}\n", 1)
    path = folder / "sim.toml"
    path.write_text(text, encoding="utf-8")
    return path


def _loads(yaml_file: Path) -> bool:
    try:
        load_map(yaml_file)
    except ConfigError:
        return False
    return True


def _save_under_way(out: Path, known: set[str]) -> bool:
    try:
        names = os.listdir(out)
    except OSError:
        return False
    return any(n.endswith(".tmp") or (n.endswith(".pgm") and n not in known) for n in names)


def content_ns(yaml_file: Path) -> int | None:
    """The content time (monotonic ns) of the map ``yaml_file`` describes, from its image's header."""
    try:
        for line in yaml_file.read_text(encoding="utf-8").splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "image":
                image = yaml_file.parent / value.split("#", 1)[0].strip().strip("'\"")
                return content_stamp_ns(image.read_bytes())
    except OSError:
        return None
    return None


def mcap_after_kill(record: Path, killed_ns: int) -> dict[str, Any]:
    """What a recording killed at ``killed_ns`` (monotonic) still reads: how many seconds before the kill
    its newest readable message is, how many messages, how many files cut."""
    newest_ns: int | None = None
    messages = cut = 0
    for _, path in recording_files(record):
        recording = read_recording(path)
        messages += len(recording.messages)
        cut += recording.stopped_at is not None
        if recording.messages:
            newest = max(m.log_time_ns for m in recording.messages)
            newest_ns = newest if newest_ns is None else max(newest_ns, newest)
    lost_s = None if newest_ns is None else round((killed_ns - newest_ns) / 1e9, 3)
    return {"mcap_lost_s": lost_s, "mcap_messages": messages, "mcap_files_cut": cut}


def kill_once(
    folder: Path, interval_s: float, delay_s: float, mid_save: bool = False, record: bool = True
) -> dict[str, Any]:
    """One mapping run in ``folder``, SIGKILLed ``delay_s`` after its first save (``mid_save``: at the
    first save under way after that); what it left."""
    out = folder / "out"
    config = mapping_config(folder, interval_s)
    command = [sys.executable, "-m", "agent.cli", "sim", "--config", str(config), "--seconds", "600"]
    command += ["--out", str(out)]
    record_path = folder / "rec" / "run.mcap"
    if record:
        command += ["--record", str(record_path)]
    proc = subprocess.Popen(
        command,
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )
    yaml_file = out / "map.yaml"
    try:
        deadline = time.monotonic() + _FIRST_SAVE_TIMEOUT_S
        while not yaml_file.exists():
            if proc.poll() is not None:
                err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
                raise RuntimeError(f"the sim ended before its first map save: {err[-2000:]}")
            if time.monotonic() > deadline:
                raise RuntimeError("no map saved in time")
            time.sleep(0.05)
        time.sleep(delay_s)
        if mid_save:
            known = set(os.listdir(out))
            deadline = time.monotonic() + 10 * interval_s + 10.0
            while not _save_under_way(out, known) and time.monotonic() < deadline:
                time.sleep(0.001)
        killed_at = time.time()
        killed_ns = time.monotonic_ns()
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        if proc.stderr is not None:
            proc.stderr.close()
    names = sorted(p.name for p in out.iterdir())
    loads = _loads(yaml_file)
    previous = out / "map.prev.yaml"
    previous_loads = _loads(previous) if previous.exists() else None
    commit_age_s = killed_at - yaml_file.stat().st_mtime
    content = content_ns(yaml_file)
    age_s = None if content is None else (killed_ns - content) / 1e9
    removed = tidy_map_folder(yaml_file)
    return {
        "delay_s": round(delay_s, 3),
        "mid_save": mid_save,
        "loads": loads,
        "previous_loads": previous_loads,
        "age_s": None if age_s is None else round(age_s, 3),
        "commit_age_s": round(commit_age_s, 3),
        "files": names,
        "left_over": [p.name for p in removed],
        "loads_after_tidy": _loads(yaml_file),
        "tmp_after_tidy": sorted(p.name for p in out.iterdir() if p.name.endswith(".tmp")),
        **(mcap_after_kill(record_path, killed_ns) if record else {}),
    }


def run(
    instants: int,
    interval_s: float,
    span_s: float,
    seed: int,
    workdir: Path,
    mid_save: int = 0,
    record: bool = True,
) -> dict[str, Any]:
    rng = random.Random(seed)
    records = []
    for k in range(instants):
        folder = workdir / f"kill{k}"
        folder.mkdir(parents=True)
        delay_s = rng.uniform(0.0, span_s)
        records.append(kill_once(folder, interval_s, delay_s, k >= instants - mid_save, record))
    ages = [r["age_s"] for r in records]
    # None when a map had no content time, or a run kept no readable message at all: worse than any figure.
    max_age_s = None if None in ages else max(ages)
    max_mcap_lost_s = (
        max(r["mcap_lost_s"] for r in records)
        if record and all(r["mcap_lost_s"] is not None for r in records)
        else None
    )
    all_loaded = all(
        r["loads"] and r["loads_after_tidy"] and r["previous_loads"] is not False for r in records
    )
    chunk_s = RecorderConfig().chunk_s  # what `vlp-agent sim --record` writes with
    checks = {
        "maps_load": {
            "bound": "every map and its previous load, nothing left as the map",
            "ok": all_loaded and all(not r["tmp_after_tidy"] for r in records),
        },
        "map_lost": {
            "bound_s": interval_s,
            "max_s": max_age_s,
            "ok": max_age_s is not None and max_age_s <= interval_s,
        },
    }
    if record:
        checks["mcap_lost"] = {
            "bound_s": chunk_s,
            "max_s": max_mcap_lost_s,
            "ok": max_mcap_lost_s is not None and max_mcap_lost_s <= chunk_s,
        }
    reasons = [f"{name}: {check}" for name, check in checks.items() if not check["ok"]]
    return {
        "instants": instants,
        "mid_save": mid_save,
        "interval_s": interval_s,
        "span_s": span_s,
        "seed": seed,
        "all_loaded": all_loaded,
        "max_age_s": max_age_s,
        "max_commit_age_s": max(r["commit_age_s"] for r in records),
        "max_left_over": max(len(r["left_over"]) for r in records),
        "max_mcap_lost_s": max_mcap_lost_s,
        "checks": checks,
        "pass": not reasons,
        "reasons": reasons,
        "records": records,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--instants", type=int, default=20)
    parser.add_argument("--mid-save", type=int, default=5, help="how many of the instants aim inside a save")
    parser.add_argument("--interval", type=float, default=1.0, help="slam.save_interval_s of the runs")
    parser.add_argument(
        "--span", type=float, default=4.0, help="kills fall U(0, SPAN) s after the first save"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--no-record", action="store_true", help="no flight recording (no mcap_lost_s): the runs as before"
    )
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="map-kill-") as tmp:
        result = run(
            args.instants, args.interval, args.span, args.seed, Path(tmp), args.mid_save, not args.no_record
        )
    print(json.dumps(result, indent=1))
    return 0 if result["pass"] else 1


if __name__ == "__main__":
    sys.exit(main())
