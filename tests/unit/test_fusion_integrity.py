"""The fusion honours the integrity of VLP fixes (agent.fusion.FixIntegrity / IntegrityPolicy and the hot
path, agent.runtime.vlp_loop): a scripted drive with nominal fixes, then wrong fixes flagged degraded or
past the alert limit (the sig100_row3 case: two LEDs read as their neighbours, ~0.9 m off, every frame
the same way). The wrong ones must not move the pose, VLP must stop counting as live, and the pose must
coast on odometry."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.config import AgentConfig
from agent.fusion import FixIntegrity, IntegrityPolicy, PoseFilter, Refusal, Source
from agent.runtime.devices import Devices
from agent.runtime.loop_state import LoopState
from agent.runtime.types import AbsoluteFix, NoFix, Prior, Tilt
from agent.runtime.vlp_loop import VlpLoop
from drivers.samples import Frame

MS = 1_000_000
SPEED = 0.2  # m/s along +x
FIX_COV = np.diag([0.004**2, 0.004**2, 0.005**2])
WRONG_OFFSET = (0.0, 0.9)  # the neighbouring pair's placement: 0.9 m across
GOOD = FixIntegrity(degraded=False, protection_level_m=0.012)
TIMEOUTS = {Source.VLP: 500 * MS, Source.ODOMETRY: 300 * MS}


def new_filter(**kw: object) -> PoseFilter:
    return PoseFilter(np.zeros(3), np.diag([0.01**2, 0.01**2, 0.01**2]), 0, **kw)  # type: ignore[arg-type]


def drive(
    f: PoseFilter, wrong: FixIntegrity | None, seconds: float = 6.0, nominal_until_s: float = 2.0
) -> list[tuple[float, float]]:
    """Odometry every 20 ms (1 % short, so the coast drifts a little), a VLP fix every 100 ms: right and
    nominal until ``nominal_until_s``, then wrong by WRONG_OFFSET with ``wrong`` integrity (None: as the
    fusion took every fix before it honoured integrity). Returns the position error after each fix."""
    errors = []
    t = 0
    for k in range(int(seconds / 0.02)):
        t0, t = t, (k + 1) * 20 * MS
        f.add_odometry(t0, t, SPEED * 0.02 * 0.99, 0.0, arrival_ns=t)
        if (k + 1) % 5:
            continue
        x_true = SPEED * t * 1e-9
        if t * 1e-9 <= nominal_until_s:
            f.add_pose(
                Source.VLP, t, x_true, 0.0, 0.0, FIX_COV, arrival_ns=t, relocalize=True, integrity=GOOD
            )
        else:
            f.add_pose(
                Source.VLP,
                t,
                x_true + WRONG_OFFSET[0],
                WRONG_OFFSET[1],
                0.0,
                FIX_COV,
                arrival_ns=t,
                relocalize=True,
                integrity=wrong,
            )
        est = f.estimate()
        errors.append(math.hypot(est.x_m - x_true, est.y_m))
    return errors


def test_without_integrity_a_run_of_agreeing_wrong_fixes_drags_the_pose_away() -> None:
    # What the fusion did before (integrity=None: every fix nominal): the wrong fixes agree with each
    # other, so the filter relocalises on them.
    f = new_filter()
    errors = drive(f, None)
    assert max(errors) > 0.8
    assert f.reset_counter >= 1


@pytest.mark.parametrize(
    "wrong",
    [
        FixIntegrity(degraded=True, protection_level_m=math.inf),  # close-signature: two LEDs, flagged
        FixIntegrity(degraded=True, protection_level_m=0.02),  # inconsistent / outlier-dropped
        FixIntegrity(degraded=False, protection_level_m=math.inf),  # nominal, but past the alert limit
    ],
    ids=["degraded-two-led", "degraded-three-led", "past-alert-limit"],
)
def test_flagged_wrong_fixes_do_not_move_the_pose(wrong: FixIntegrity) -> None:
    f = new_filter()
    errors = drive(f, wrong)
    # Nothing wrong fused: the coast's error is the odometry's 1 % over the last 0.8 m, under 1 cm.
    assert max(errors) < 0.012
    assert f.reset_counter == 0
    counts = f.counters()
    expected = Refusal.INTEGRITY if wrong.degraded else Refusal.ALERT_LIMIT
    assert counts[f"vlp_refused_{expected}"] == 40  # 4 s of fixes at 10 Hz, every one refused
    assert counts.get("vlp_fused_guarded", 0) == 0
    assert counts["vlp_fused"] == 20
    # The status: VLP is not live (an integrity alert) while odometry carries the pose.
    now = 6000 * MS
    assert f.integrity_alert(Source.VLP)
    assert f.live(now, TIMEOUTS) == {Source.ODOMETRY}


def test_refused_fixes_take_vlp_off_at_its_timeout_and_a_fused_one_puts_it_back() -> None:
    f = new_filter()
    cov = FIX_COV
    f.add_pose(Source.VLP, 10 * MS, 0.0, 0.0, 0.0, cov, arrival_ns=10 * MS, integrity=GOOD)
    assert f.live(20 * MS, TIMEOUTS) == {Source.VLP}
    for k in range(12):  # 600 ms of refused fixes: nothing fused, as if none came
        t = (60 + 50 * k) * MS
        r = f.add_pose(
            Source.VLP, t, 0.0, 0.9, 0.0, cov, arrival_ns=t, integrity=FixIntegrity(True, math.inf)
        )
        assert not r.accepted and r.guarded and r.refused is Refusal.INTEGRITY
        assert f.integrity_alert(Source.VLP)
    assert f.live(500 * MS, TIMEOUTS) == {Source.VLP}  # the last fused fix is within the timeout
    assert f.live(600 * MS, TIMEOUTS) == set()
    r = f.add_pose(Source.VLP, 650 * MS, 0.0, 0.0, 0.0, cov, arrival_ns=650 * MS, integrity=GOOD)
    assert r.accepted and not r.guarded and r.refused is Refusal.NONE
    assert f.live(660 * MS, TIMEOUTS) == {Source.VLP}
    assert not f.integrity_alert(Source.VLP)


def test_acquisition_the_first_unflagged_fix_past_the_alert_limit_is_checked_by_the_gate_alone() -> None:
    # At start the pose is the configured guess (here 5 cm): no window within the alert limit, and no
    # other source to check a fix with. An unflagged two-LED fix within the gate is taken (inflated);
    # after it the window applies. A flagged one is refused all the same.
    f = PoseFilter(np.zeros(3), np.diag([0.05**2, 0.05**2, 0.03**2]), 0)
    r = f.add_pose(Source.VLP, 10 * MS, 0.0, 0.0, 0.0, FIX_COV, integrity=FixIntegrity(True, math.inf))
    assert not r.accepted and r.refused is Refusal.INTEGRITY
    r = f.add_pose(Source.VLP, 20 * MS, 0.9, 0.0, 0.0, FIX_COV, integrity=FixIntegrity(False, math.inf))
    assert not r.accepted and r.refused is Refusal.ALERT_LIMIT  # outside the gate
    r = f.add_pose(Source.VLP, 30 * MS, 0.02, 0.0, 0.0, FIX_COV, integrity=FixIntegrity(False, math.inf))
    assert r.accepted and r.guarded
    assert f.estimate().sigma_xy_m < 0.025


@pytest.mark.parametrize("fuse_degraded", [False, True])
def test_a_right_fix_past_the_alert_limit_is_fused_under_the_guard_with_less_weight(
    fuse_degraded: bool,
) -> None:
    # A two-LED fix (PL infinite) that agrees with a well-known prediction is used, inflated: it pulls the
    # pose far less than the same fix taken as nominal would (sigma_scale 3: weight 1/9). A degraded one
    # is refused, unless the policy says to guard those too.
    offset = 0.01

    def pulled(integrity: FixIntegrity) -> float:
        f = new_filter(integrity=IntegrityPolicy(fuse_degraded=fuse_degraded))
        for k in range(10):  # settle the filter on nominal fixes at the origin
            f.add_pose(Source.VLP, (k + 1) * 10 * MS, 0.0, 0.0, 0.0, FIX_COV, integrity=GOOD)
        r = f.add_pose(Source.VLP, 110 * MS, offset, 0.0, 0.0, FIX_COV, integrity=integrity)
        assert r.guarded == (integrity is not GOOD)
        assert r.accepted == (not integrity.degraded or fuse_degraded)
        return f.estimate().x_m

    nominal = pulled(GOOD)
    guarded = pulled(FixIntegrity(False, math.inf))
    assert 0.0 < guarded < 0.5 * nominal
    degraded = pulled(FixIntegrity(True, math.inf))
    assert degraded == pytest.approx(guarded if fuse_degraded else 0.0, abs=1e-12)


def test_guarded_fixes_are_refused_once_the_prediction_cannot_check_them_to_the_alert_limit() -> None:
    # After a long coast the prediction is too uncertain for its gate to bound a fix within the alert
    # limit: even a right guarded fix is refused (it could be 0.9 m off and still pass).
    f = new_filter(integrity=IntegrityPolicy(fuse_degraded=True))
    f.add_pose(Source.VLP, 10 * MS, 0.0, 0.0, 0.0, FIX_COV, integrity=GOOD)
    t = 10 * MS
    for _ in range(300):  # 6 s without odometry: the position random walk grows the covariance
        t += 20 * MS
        f.add_gyro(t, 0.0)
    assert f.estimate().sigma_xy_m > 0.05
    r = f.add_pose(Source.VLP, t + MS, 0.0, 0.0, 0.0, FIX_COV, integrity=FixIntegrity(True, 0.02))
    assert not r.accepted and r.refused is Refusal.INTEGRITY
    r = f.add_pose(Source.VLP, t + MS, 0.0, 0.0, 0.0, FIX_COV, integrity=FixIntegrity(False, math.inf))
    assert not r.accepted and r.refused is Refusal.ALERT_LIMIT
    # A nominal fix within the alert limit is fused as before (the ordinary gate).
    r = f.add_pose(Source.VLP, t + 2 * MS, 0.0, 0.0, 0.0, FIX_COV, integrity=GOOD)
    assert r.accepted and not r.guarded


def test_sigma_scale_zero_refuses_every_guarded_fix_and_the_policy_is_checked() -> None:
    f = new_filter(integrity=IntegrityPolicy(alert_limit_m=0.10, sigma_scale=0.0, fuse_degraded=True))
    f.add_pose(Source.VLP, 10 * MS, 0.0, 0.0, 0.0, FIX_COV, integrity=GOOD)
    r = f.add_pose(Source.VLP, 20 * MS, 0.0, 0.0, 0.0, FIX_COV, integrity=FixIntegrity(True, 0.01))
    assert not r.accepted and r.refused is Refusal.INTEGRITY
    r = f.add_pose(Source.VLP, 30 * MS, 0.0, 0.0, 0.0, FIX_COV, integrity=FixIntegrity(False, math.inf))
    assert not r.accepted and r.refused is Refusal.ALERT_LIMIT
    # An alert limit of 1 cm makes a 1.2 cm protection level too much.
    g = new_filter(integrity=IntegrityPolicy(alert_limit_m=0.01))
    r = g.add_pose(Source.VLP, 10 * MS, 0.0, 0.0, 0.0, FIX_COV, integrity=GOOD)
    assert r.guarded
    for bad in ({"alert_limit_m": 0.0}, {"alert_limit_m": math.inf}, {"sigma_scale": 0.5}):
        with pytest.raises(ValueError):
            IntegrityPolicy(**bad)  # type: ignore[arg-type]


def test_the_integrity_policy_and_the_fixes_integrity_replay_from_a_recording() -> None:
    from agent.runtime.recorder import replay_records

    records: list[dict[str, object]] = []
    policy = IntegrityPolicy(alert_limit_m=0.05, sigma_scale=2.0, fuse_degraded=True)
    f = new_filter(observer=records.append, integrity=policy)
    drive(f, FixIntegrity(True, math.inf), seconds=3.0)
    est = f.estimate()
    header = {"k": "header", "fusion": f.parameters}
    out = {"k": "out", "v": f.inputs, "t": est.t_ns, "x": est.x_m, "y": est.y_m, "yaw": est.yaw_rad}
    result = replay_records([header, *records, out])
    assert result.outputs == 1
    assert result.max_position_difference_m == 0.0


# -- the hot path: the same stream through VlpLoop.locate ------------------------------------------------
class ScriptedLocalizer:
    """Hands back the fixes of a script, one per frame, whatever the frame."""

    name = "vlp"

    def __init__(self, fixes: list[AbsoluteFix]) -> None:
        self.fixes = iter(fixes)

    def process(self, frame: Frame, tilt: Tilt | None, prior: Prior | None) -> AbsoluteFix | NoFix:
        fix = next(self.fixes)
        assert fix.t_ns == frame.host_time_ns
        return fix


def test_the_hot_path_does_not_fuse_flagged_wrong_fixes() -> None:
    """Fails on the code before integrity was honoured: the wrong fixes were fused (and relocalised on)."""
    clock = [0]
    state = LoopState(AgentConfig("test", {}), Devices(), lambda: clock[0])
    fusion = new_filter()
    times = [(k + 1) * 50 * MS for k in range(100)]
    fixes = []
    for t in times:
        x_true = SPEED * t * 1e-9
        wrong = t > 2000 * MS
        fixes.append(
            AbsoluteFix(
                t,
                x_true + (WRONG_OFFSET[0] if wrong else 0.0),
                WRONG_OFFSET[1] if wrong else 0.0,
                0.0,
                FIX_COV,
                degraded=wrong,
                detail={"flags": ("close-signature",) if wrong else ()},
                protection_level_m=math.inf if wrong else 0.012,
            )
        )
    published: list[int | None] = []
    loop = VlpLoop(
        state,
        localizer=ScriptedLocalizer(fixes),
        fusion=fusion,
        frames=None,  # type: ignore[arg-type]  # locate() takes its frame directly
        hot_path=None,  # type: ignore[arg-type]
        collector=None,  # type: ignore[arg-type]
        tilt=None,
        slam_fixes=None,
        publish=lambda trigger, arrival: published.append(trigger),
    )
    image = np.zeros((2, 2), dtype=np.uint8)
    t_prev = 0
    for k, t in enumerate(times):
        for j in range(1, 6):  # odometry every 10 ms up to the frame, 1 % short
            t0, t1 = t_prev + (j - 1) * 10 * MS, t_prev + j * 10 * MS
            fusion.add_odometry(t0, t1, SPEED * 0.01 * 0.99, 0.0, arrival_ns=t1)
        t_prev = t
        clock[0] = t
        loop.locate(Frame(image, k, t), t)
        est = fusion.estimate()
        assert math.hypot(est.x_m - SPEED * t * 1e-9, est.y_m) < 0.015, f"pose dragged at frame {k}"
    assert fusion.reset_counter == 0
    assert state.counts["fixes_fused"] == 40
    assert state.counts["fixes_rejected_integrity"] == 60
    assert published == times[:40]  # a refused fix writes no pose of its own
    assert Source.VLP not in fusion.live(times[-1], TIMEOUTS)
