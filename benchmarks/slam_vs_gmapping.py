"""Our SLAM beside GMapping's C++ core on the same logs, scored by the same metric code; prints JSON.

GMapping (``openslam_gmapping``, the core behind ROS's slam_gmapping, with slam_gmapping's defaults) is
built from ``../shared/peers/gmapping/`` (its ``build.sh``) into a cache folder outside the repository;
each log is written in that driver's input format from our own log readers (``agent.slam.logs``), so
both systems get the same beams and the same odometry. Per log and seed, ours then GMapping (alternately,
so a machine busy with other work slows both alike), each in its own process (peak RSS is then each one's
own): the whole log's wall time and CPU time, the median filter update, peak RSS, and the metrics. The
verdict on speed is ``cpu_ratio`` (ours / GMapping's CPU seconds over the whole log: the filter's
process time, GMapping's driver's loop thread), which the machine's other work moves far less than
``wall_ratio`` (beside it):

* radish logs (Intel, ACES, FR079): ``ate_aligned_m`` (RMS position error against the file's reference
  poses, GMapping's own published output, after the best rigid alignment), the consecutive relations, the
  ``span_*`` relations (pairs ``--span`` records apart) and ``relation_over_10m_m`` / ``_deg`` (every pair
  further apart than 10 m: does the map hold together across the building);
* exp1 (no reference): whether the loop closes, the measure of ``tests/integration/test_slam_exp1.py``
  (imported from it) on the first 365 records of the whole-log run: closed when the revisit is within
  0.1 m and 2 deg of a direct registration on the first map.

With ``--repeat N`` each system runs N times per log and seed, the order alternating from round to round;
the times are then the medians (each run's listed beside them, ``cpu_ratio_rounds`` each round's ratio),
the accuracy the first run's (``repeats_differ`` flags a system whose runs gave other poses).

GMapping is skipped, with the reason in the JSON, where ``../shared/peers/gmapping`` or a C++ compiler is
absent or the build fails; a log whose file is absent is skipped the same way.

    nice -n 15 python benchmarks/slam_vs_gmapping.py --logs intel aces --seeds 0 1 2 --out intel_aces.json
    nice -n 15 python benchmarks/slam_vs_gmapping.py --logs exp1 --seeds 0 1 2 3 4 5
    python benchmarks/slam_vs_gmapping.py --logs exp1 --seeds 0 1 2 3 4 5 --repeat 3
    python benchmarks/slam_vs_gmapping.py --logs intel --seeds 0 --no-gmapping
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np
import numpy.typing as npt

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from agent.slam.logs import LogFormat, SlamLog, read_log  # noqa: E402

FloatArray = npt.NDArray[np.float64]

SHARED = Path(os.environ.get("VLP_SHARED", REPO.parent / "shared"))
PEER = SHARED / "peers" / "gmapping"
LOGS: dict[str, tuple[str, LogFormat]] = {
    "intel": ("slam/radish/intel_scans.txt", LogFormat.RADISH),
    "aces": ("slam/radish/aces_scans.txt", LogFormat.RADISH),
    "fr079": ("slam/radish/freiburg-079_scans.txt", LogFormat.RADISH),
    "exp1": ("slam/breezyslam/exp1.dat", LogFormat.BREEZYSLAM),
}
EXP1_LOOP_RECORDS = 365


# -- GMapping's input format (../shared/peers/gmapping/README.md) -----------------------------------------


@dataclasses.dataclass(frozen=True)
class GmappingInput:
    """What the driver reads back: the header and one row per record."""

    beams: int
    angle0_rad: float
    dangle_rad: float
    mount: tuple[float, float, float]
    range_min_m: float
    range_max_m: float
    times_s: FloatArray
    odometry: FloatArray  # (N, 3)
    ranges_m: FloatArray  # (N, beams), 0 = no return


def gmapping_lines(log: SlamLog) -> list[str]:
    """The log in the driver's format: ``n_beams angle0_rad dangle_rad mount_x mount_y mount_yaw range_min
    range_max``, then ``t odo_x odo_y odo_th r_0 ... r_{n-1}`` per record, no return written as 0 (our
    convention: below ``min_range_m`` or at/above ``no_return_m``)."""
    g = log.geometry
    angles = g.angles_rad
    steps = np.diff(angles)
    if not np.allclose(steps, steps[0], atol=1e-9):
        raise ValueError("GMapping needs evenly spaced beams")
    header = (
        f"{g.beams} {angles[0]:.12f} {steps[0]:.12f} {g.mount[0]:.6f} {g.mount[1]:.6f} {g.mount[2]:.9f} "
        f"{g.min_range_m:.6f} {g.no_return_m:.6f}"
    )
    lines = [header]
    for record in log.records:
        ranges = np.where(
            (record.ranges_m < g.min_range_m) | (record.ranges_m >= g.no_return_m), 0.0, record.ranges_m
        )
        x, y, th = record.odom_pose
        values = " ".join(f"{r:.6g}" for r in ranges)
        lines.append(f"{record.t_s:.6f} {x:.9f} {y:.9f} {th:.9f} {values}")
    return lines


def write_gmapping_input(log: SlamLog, path: Path) -> Path:
    path.write_text("\n".join(gmapping_lines(log)) + "\n", encoding="ascii")
    return path


def read_gmapping_input(path: Path) -> GmappingInput:
    with path.open(encoding="ascii") as handle:
        head = handle.readline().split()
        rows = np.loadtxt(handle, dtype=np.float64, ndmin=2)
    beams = int(head[0])
    a0, da, mx, my, myaw, rmin, rmax = (float(v) for v in head[1:8])
    return GmappingInput(
        beams, a0, da, (mx, my, myaw), rmin, rmax, rows[:, 0], rows[:, 1:4], rows[:, 4 : 4 + beams]
    )


# -- building and running GMapping -------------------------------------------------------------------------


def default_build_dir() -> Path:
    cache = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"))
    return cache / "vlp-agent" / "gmapping-5105476"


def build_gmapping(peer: Path, build_dir: Path, compiler: str | None = None) -> tuple[Path | None, str]:
    """(the driver, "") or (None, why not): the build is skipped, never fatal."""
    script = peer / "build.sh"
    if not script.is_file():
        return None, f"GMapping's sources not found ({script} is absent; set VLP_SHARED)"
    cxx = compiler or os.environ.get("CXX", "g++")
    if shutil.which(cxx) is None:
        return None, f"no C++ compiler ({cxx!r} not on PATH) to build GMapping"
    driver = build_dir / "gmapping_run"
    if driver.is_file() and driver.stat().st_mtime >= max(
        p.stat().st_mtime for p in peer.rglob("*") if p.is_file()
    ):
        return driver, ""
    done = subprocess.run(
        ["sh", str(script), str(build_dir)],
        capture_output=True,
        text=True,
        env={**os.environ, "CXX": cxx},
        check=False,
    )
    if done.returncode != 0 or not driver.is_file():
        tail = (done.stderr or done.stdout).strip().splitlines()[-3:]
        return None, f"GMapping's build failed (exit {done.returncode}): {' | '.join(tail)}"
    return driver, ""


def run_gmapping(
    driver: Path, log_file: Path, out_prefix: Path, particles: int, seed: int, urange_frac: float
) -> tuple[FloatArray, dict[str, Any]]:
    subprocess.run(
        [str(driver), str(log_file), str(out_prefix), str(particles), str(urange_frac), str(seed + 1)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        check=True,
    )
    poses = np.loadtxt(f"{out_prefix}_traj.txt", ndmin=2)
    times = np.loadtxt(f"{out_prefix}_times.txt", ndmin=2)
    summary = dict(
        line.split("=", 1) for line in Path(f"{out_prefix}_summary.txt").read_text().splitlines() if line
    )
    updates = times[times[:, 1] == 1, 2]
    return poses, {
        "wall_s": round(float(summary["loop_wall_s"]), 3),
        "cpu_s": round(float(summary["loop_cpu_s"]), 3),
        "update_ms_median": round(float(np.median(updates)), 2) if updates.size else None,
        "updates": int(updates.size),
        "peak_rss_mb": round(int(summary["loop_peak_rss_kb"]) / 1024.0, 1),
    }


# -- ours, in a process of its own --------------------------------------------------------------------------


def graph_knobs(args: argparse.Namespace) -> list[str]:
    """The pose-graph options of ``args`` as command-line arguments again (for the worker)."""
    out: list[str] = []
    if args.edge_sigma is not None:
        out += ["--edge-sigma", *(str(v) for v in args.edge_sigma)]
    if args.match_sigma is not None:
        out += ["--match-sigma", str(args.match_sigma)]
    return out


def ours_worker(
    log_path: str,
    log_format: str,
    seed: int,
    particles: int,
    out_npy: str,
    loop_closure: bool = True,
    edge_sigma: Sequence[float] | None = None,
    match_sigma: float | None = None,
) -> int:
    """Run our filter as ``vlp-agent eval slam --log`` configures it (``edge_sigma``, ``match_sigma``: the
    loop closure's ``motion_sigma`` and ``match_sigma_m`` instead of the defaults); save the poses, print
    the figures."""
    import cv2

    from agent.commands.eval_slam import log_config
    from agent.slam.malloc import tune_malloc
    from agent.slam.replay import replay

    cv2.setNumThreads(1)
    tune_malloc()  # as the robot's SLAM process (agent.runtime.slam_worker) does
    log = read_log(log_path, log_format)
    config = log_config(log_format, seed=seed, particles=particles, loop_closure=loop_closure)
    if config.loop_closure is not None and (edge_sigma is not None or match_sigma is not None):
        loop = config.loop_closure
        if edge_sigma is not None:
            loop = dataclasses.replace(loop, motion_sigma=tuple(edge_sigma))
        if match_sigma is not None:
            loop = dataclasses.replace(loop, match_sigma_m=match_sigma)
        config = dataclasses.replace(config, loop_closure=loop)
    result = replay(log, config)
    np.save(out_npy, result.poses)
    slam = result.slam
    print(
        json.dumps(
            {
                "wall_s": round(result.wall_s, 3),
                "cpu_s": round(result.cpu_s, 3),
                "update_ms_median": round(float(np.median(result.update_ms)), 2),
                "updates": slam.stats.updates,
                "peak_rss_mb": round(peak_rss_kb() / 1024.0, 1),
                **{f"{k}_end_mb": round(v / 1024.0, 1) for k, v in rss_parts_kb().items()},
                "resamples": slam.stats.resamples,
                "match_failures": slam.stats.match_failures,
                **slam_extras(slam),
            }
        )
    )
    return 0


def _status_kb(keys: tuple[str, ...]) -> dict[str, float]:
    """The fields ``keys`` of /proc/self/status in kB (absent: a field it lacks, or all where it cannot
    be read)."""
    try:
        lines = Path("/proc/self/status").read_text().splitlines()
    except OSError:
        return {}
    fields = (line.split(":", 1) for line in lines if ":" in line)
    return {key: float(value.split()[0]) for key, value in fields if key in keys}


def peak_rss_kb() -> float:
    """This process's peak resident memory (VmHWM, as GMapping's driver reads it). Not ``ru_maxrss``:
    Linux carries that across ``exec`` from the forking parent, so a child of a benchmark that has read
    several logs would report the parent's peak (exp1 measured 285.8 MB that way, 107 MB alone)."""
    peak = _status_kb(("VmHWM",)).get("VmHWM")
    return peak if peak is not None else float(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)


def rss_parts_kb() -> dict[str, float]:
    """This process's resident memory now, split: ``rss_anon`` (its own data: heap, arrays) and
    ``rss_file`` (pages of mapped files, mostly the shared libraries: OpenCV's alone is ~15 MB).
    ``peak_rss_mb`` moves with the machine's state for the same poses (docs/slam.md, "Running it")."""
    parts = _status_kb(("RssAnon", "RssFile"))
    return {key.lower().replace("rss", "rss_"): kb for key, kb in parts.items()}


def slam_extras(slam: Any) -> dict[str, Any]:
    """Loop-closure counters."""
    stats = slam.stats
    return {
        "loop_closures": stats.loop_closures,
        "loop_rebuilds": stats.loop_rebuilds,
        "loop_verdicts": dict(sorted(stats.loop_verdicts.items())),
        "loop_s": round(stats.loop_ms / 1e3, 2),
    }


def run_ours(
    log_path: Path,
    log_format: LogFormat,
    seed: int,
    particles: int,
    out_npy: Path,
    loop_closure: bool,
    knobs: Sequence[str] = (),
) -> tuple[FloatArray, dict[str, Any]]:
    done = subprocess.run(
        [
            sys.executable,
            __file__,
            "--worker",
            str(log_path),
            log_format.value,
            str(seed),
            str(particles),
            str(out_npy),
            "--loop-closure",
            "on" if loop_closure else "off",
            *knobs,
        ],
        capture_output=True,
        text=True,
        check=True,
    )
    figures: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    return np.load(out_npy), figures


def combine_runs(results: Sequence[tuple[FloatArray, dict[str, Any]]]) -> dict[str, Any]:
    """One system's figures over repeated runs of the same log and seed (``--repeat``): the first run's,
    with the times (``wall_s``, ``cpu_s``, ``update_ms_median``) the median over the runs and each run's
    beside them (``wall_s_runs``, ``cpu_s_runs``). Both systems are seeded, so every run should give the
    same poses; ``repeats_differ`` says where they did not (the accuracy figures are the first run's)."""
    if not results:
        raise ValueError("no runs to combine")
    first_poses, first = results[0]
    out = dict(first)
    for key in ("wall_s", "cpu_s", "update_ms_median"):
        values = [figures[key] for _poses, figures in results]
        if any(v is None for v in values):
            continue
        out[key] = round(float(np.median(values)), 3)
        if key != "update_ms_median" and len(results) > 1:
            out[f"{key}_runs"] = values
    if len(results) > 1:
        out["repeats_differ"] = any(
            poses.shape != first_poses.shape or not np.array_equal(poses, first_poses)
            for poses, _figures in results[1:]
        )
    return out


# -- scoring ------------------------------------------------------------------------------------------------


def score(log: SlamLog, poses: FloatArray, span: int) -> dict[str, Any]:
    """The same measures for either system's poses (one per record)."""
    from agent.slam.metrics import aligned_trajectory_error, far_relation_error, relative_pose_error

    reference = log.reference_poses()
    if reference is not None:
        first = np.arange(max(len(log) - span, 0))
        spans = relative_pose_error(reference, poses, np.stack([first, first + span], axis=1))
        far = far_relation_error(reference, poses)
        consecutive = relative_pose_error(reference, poses)
        return {
            "ate_aligned_m": round(aligned_trajectory_error(reference, poses), 4),
            "trans_error_m_mean": round(consecutive.trans_error_m_mean, 4),
            "span_trans_error_m_mean": round(spans.trans_error_m_mean, 4),
            "span_rot_error_deg_mean": round(spans.rot_error_deg_mean, 3),
            "relation_over_10m_m": round(far.trans_error_m_mean, 4),
            "relation_over_10m_deg": round(far.rot_error_deg_mean, 3),
        }
    from tests.integration.test_slam_exp1 import loop_closure_errors

    loop_m, loop_deg, _ = loop_closure_errors(log.sliced(0, EXP1_LOOP_RECORDS), poses[:EXP1_LOOP_RECORDS])
    return {
        "loop_error_m": round(loop_m, 3),
        "loop_error_deg": round(loop_deg, 2),
        "loop_closed": bool(loop_m < 0.1 and loop_deg < 2.0),
    }


def machine() -> dict[str, Any]:
    """What the ratios were measured on: the same code gives another ``cpu_ratio`` on another CPU or
    Python build (docs/slam.md, "Measurements": 0.41-0.46 on one machine, 0.54-0.60 on another), so the
    JSON names the CPU, the interpreter and the libraries beside the figures."""
    import platform

    import cv2
    import scipy

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    cxx = os.environ.get("CXX", "g++")
    compiler = None
    if shutil.which(cxx) is not None:
        done = subprocess.run([cxx, "--version"], capture_output=True, text=True, check=False)
        compiler = (done.stdout.splitlines() or [None])[0]
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "python": f"{platform.python_implementation()} {platform.python_version()}",
        "python_build": f"{platform.python_compiler()}, {' '.join(platform.python_build())}",
        "python_executable": sys.executable,
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "opencv": cv2.__version__,
        "gmapping_compiler": compiler,
    }


def benchmark(args: argparse.Namespace) -> dict[str, Any]:
    work = Path(tempfile.mkdtemp(prefix="slam-vs-gmapping-"))
    driver: Path | None = None
    skip_reason = "--no-gmapping"
    if not args.no_gmapping:
        driver, skip_reason = build_gmapping(Path(args.peer), Path(args.build_dir))
    out: dict[str, Any] = {
        "particles": args.particles,
        "seeds": args.seeds,
        "span": args.span,
        "loop_closure": args.loop_closure,
        "edge_sigma": args.edge_sigma,
        "match_sigma": args.match_sigma,
        "repeat": args.repeat,
        "machine": machine(),
        "gmapping": {"driver": str(driver), "urange_frac": args.urange_frac}
        if driver
        else {"skipped": skip_reason},
        "logs": {},
    }
    for name in args.logs:
        relative, log_format = LOGS[name]
        path = SHARED / "data" / relative
        if not path.is_file():
            out["logs"][name] = {"skipped": f"log not found: {path}"}
            continue
        log = read_log(path, log_format)
        gm_input = write_gmapping_input(log, work / f"{name}.gmlog") if driver else None
        runs = []
        for k, seed in enumerate(args.seeds):
            row: dict[str, Any] = {"seed": seed}
            done: dict[str, list[tuple[FloatArray, dict[str, Any]]]] = {"ours": [], "gmapping": []}
            for round_ in range(args.repeat):
                order = ("ours", "gmapping") if (k + round_) % 2 == 0 else ("gmapping", "ours")
                for system in order:
                    if system == "ours":
                        done["ours"].append(
                            run_ours(
                                path,
                                log_format,
                                seed,
                                args.particles,
                                work / "ours.npy",
                                args.loop_closure == "on",
                                graph_knobs(args),
                            )
                        )
                    elif driver is not None and gm_input is not None:
                        done["gmapping"].append(
                            run_gmapping(
                                driver,
                                gm_input,
                                work / f"gm_{name}_{seed}",
                                args.particles,
                                seed,
                                args.urange_frac,
                            )
                        )
            for system, results in done.items():
                if results:
                    row[system] = {**combine_runs(results), **score(log, results[0][0], args.span)}
            if "gmapping" in row:
                row["wall_ratio"] = round(row["ours"]["wall_s"] / row["gmapping"]["wall_s"], 3)
                row["cpu_ratio"] = round(row["ours"]["cpu_s"] / row["gmapping"]["cpu_s"], 3)
                row["update_ratio"] = round(
                    row["ours"]["update_ms_median"] / row["gmapping"]["update_ms_median"], 3
                )
                if args.repeat > 1:
                    row["cpu_ratio_rounds"] = [
                        round(a / b, 3)
                        for a, b in zip(row["ours"]["cpu_s_runs"], row["gmapping"]["cpu_s_runs"], strict=True)
                    ]
            print(json.dumps({"log": name, **row}), file=sys.stderr, flush=True)
            runs.append(row)
        out["logs"][name] = {"records": len(log), "runs": runs}
    shutil.rmtree(work, ignore_errors=True)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--worker", nargs=5, metavar=("LOG", "FORMAT", "SEED", "PARTICLES", "OUT"))
    parser.add_argument("--logs", nargs="+", choices=sorted(LOGS), default=["intel", "aces", "fr079", "exp1"])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--particles", type=int, default=30)
    parser.add_argument(
        "--repeat",
        type=int,
        default=1,
        help="runs of each system per log and seed, the order alternating from round to round; the "
        "times are then the medians (each run's beside them) and cpu_ratio their ratio (default 1)",
    )
    parser.add_argument("--span", type=int, default=50, help="records between the span_* pairs")
    parser.add_argument(
        "--urange-frac", type=float, default=0.8, help="GMapping's maxUrange / maxRange (driver default)"
    )
    parser.add_argument("--peer", default=str(PEER), help="GMapping's sources and build.sh")
    parser.add_argument("--build-dir", default=str(default_build_dir()), help="where GMapping is built")
    parser.add_argument("--no-gmapping", action="store_true", help="run ours only")
    parser.add_argument(
        "--loop-closure", choices=("on", "off"), default="on", help="ours with loop closure or without"
    )
    parser.add_argument(
        "--edge-sigma",
        type=float,
        nargs=3,
        metavar=("X", "Y", "YAW"),
        help="ours: the pose graph's front-end edge sigmas (LoopClosureConfig.motion_sigma)",
    )
    parser.add_argument(
        "--match-sigma", type=float, help="ours: loop factors with the match's covariance (match_sigma_m)"
    )
    parser.add_argument("--out", help="also write the JSON here")
    args = parser.parse_args(argv)
    if args.repeat < 1:
        parser.error(f"--repeat must be at least 1, got {args.repeat}")
    if args.worker:
        log_path, log_format, seed, particles, out_npy = args.worker
        return ours_worker(
            log_path,
            log_format,
            int(seed),
            int(particles),
            out_npy,
            args.loop_closure == "on",
            args.edge_sigma,
            args.match_sigma,
        )
    started = time.time()
    result = benchmark(args)
    result["elapsed_s"] = round(time.time() - started, 1)
    text = json.dumps(result, indent=1)
    if args.out:
        Path(args.out).write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
