"""Map and topology snapshots over the fleet: the local frames, the network payloads (strict, capped), the
merge and the pairwise agreement, the picture; and the agent's fleet loop handing its map to a bridge
(a real Unix socket, the in-memory Zenoh stand-in of test_fleet_bridge). No network, no wall-clock
assertion."""

from __future__ import annotations

import base64
import json
import zlib
from pathlib import Path

import numpy as np
import pytest

from agent.fleet import audit, payloads
from agent.fleet.local_protocol import (
    HEADER,
    MAGIC,
    MAX_SNAPSHOT_PAYLOAD,
    VERSION,
    FrameDecoder,
    LocalProtocolError,
    MapMessage,
    PoseMessage,
    TopologyMessage,
    decode_frame,
    encode,
)
from agent.fleet.map_view import FleetMaps, picture, report
from agent.fleet.maps import FREE, OCCUPIED, UNKNOWN, Grid, agreement, grid_from_image, merge
from agent.slam.render import OccupancyImage
from tests.fleet_helpers import FleetThreads

RES = 0.05


def _room(h: int = 60, w: int = 80) -> np.ndarray:
    """A walled room with an inner wall, unknown around it."""
    g = np.full((h, w), UNKNOWN, np.int8)
    g[5:-5, 5:-5] = FREE
    g[5, 5:-5] = g[-6, 5:-5] = OCCUPIED
    g[5:-5, 5] = g[5:-5, -6] = OCCUPIED
    g[20:45, 40] = OCCUPIED
    return g


def _message(cells: np.ndarray, path: tuple[tuple[float, float], ...] = ((1.0, 1.0),)) -> MapMessage:
    h, w = cells.shape
    return MapMessage(7, RES, 1.0, 2.0, w, h, zlib.compress(cells.tobytes()), path)


def test_map_frame_round_trip_and_caps() -> None:
    m = _message(_room(), ((1.0, 2.0), (1.5, 2.25)))
    frame = encode(m)
    assert frame[2] == VERSION == 3
    assert decode_frame(frame) == m
    assert np.array_equal(np.frombuffer(m.cells(), np.int8).reshape(60, 80), _room())
    # Larger than the small messages' 1024-byte cap is fine for a snapshot, over its own cap is not.
    header = HEADER.pack(MAGIC, VERSION, MapMessage.TYPE, MAX_SNAPSHOT_PAYLOAD + 1)
    with pytest.raises(LocalProtocolError, match="at most"):
        FrameDecoder().feed(header)
    topo = TopologyMessage(5, b'{"type":"FeatureCollection","features":[]}')
    assert decode_frame(encode(topo)) == topo


@pytest.mark.parametrize(
    "cells_zlib",
    [
        zlib.compress(b"\x00" * (60 * 80 - 1)),  # one cell short
        zlib.compress(b"\x00" * (60 * 80 + 1)),  # one too many
        zlib.compress(bytes([50] * 4799 + [101])),  # a value outside -1..100
        b"not zlib at all",
        zlib.compress(b"\x00" * 10_000_000),  # a bomb: stopped at the grid's size
    ],
)
def test_bad_map_cells_refused(cells_zlib: bytes) -> None:
    bad = MapMessage(7, RES, 1.0, 2.0, 80, 60, cells_zlib)
    with pytest.raises(LocalProtocolError):
        decode_frame(encode(bad))


def test_map_payload_strict() -> None:
    data = payloads.encode_map("r1", _message(_room()))
    got = payloads.decode_map(data, "r1")
    assert (
        np.array_equal(got.grid.cells, _room()) and got.grid.origin_x_m == 1.0 and got.path == ((1.0, 1.0),)
    )
    with pytest.raises(payloads.FleetPayloadError):
        payloads.decode_map(data, "r2")  # under another robot's key
    obj = json.loads(data)
    for field, value in [
        ("frame", "odom"),
        ("width", 81),
        ("resolution_m", -0.05),
        ("cells", "!!"),
        ("cells", base64.b64encode(zlib.compress(b"\x00" * 10)).decode()),
        ("path", [[1.0, "x"]]),
        ("encoding", "png"),
    ]:
        with pytest.raises(payloads.FleetPayloadError):
            payloads.decode_map(json.dumps({**obj, field: value}).encode(), "r1")
    with pytest.raises(payloads.FleetPayloadError, match="at most"):
        payloads.decode_map(b" " * (payloads.MAX_MAP_PAYLOAD + 1), "r1")


def test_topology_payload_strict() -> None:
    geo = {
        "type": "FeatureCollection",
        "features": [
            {
                "type": "Feature",
                "geometry": {"type": "Point", "coordinates": [1.0, 2.0]},
                "properties": {"id": 0},
            },
            {
                "type": "Feature",
                "geometry": {"type": "MultiLineString", "coordinates": [[[1.0, 2.0], [3.0, 2.0]]]},
                "properties": {"id": 2, "startid": 0, "endid": 1},
            },
        ],
    }
    data = payloads.encode_topology("r1", TopologyMessage(3, json.dumps(geo).encode()))
    assert payloads.decode_topology(data, "r1") == geo
    bad = json.loads(data)
    bad["topology"]["features"][0]["geometry"] = {"type": "Image", "coordinates": [1.0, 2.0]}
    with pytest.raises(payloads.FleetPayloadError):
        payloads.decode_topology(json.dumps(bad).encode(), "r1")
    with pytest.raises(payloads.FleetPayloadError):
        payloads.encode_topology("r1", TopologyMessage(3, b'{"type":"FeatureCollection","features":[1]}'))


def test_grid_from_image_flips_rows_and_thresholds() -> None:
    pixels = np.array([[0, 254], [205, 254]], np.uint8)  # top row: occupied, free
    g = grid_from_image(pixels, RES, (1.0, 2.0))
    assert g.cells.tolist() == [[UNKNOWN, FREE], [OCCUPIED, FREE]]  # row 0 = lowest y


def test_merge_occupied_wins_unknown_where_nobody_saw() -> None:
    a = np.full((4, 4), UNKNOWN, np.int8)
    b = a.copy()
    a[0, :2] = FREE
    b[0, 1:3] = OCCUPIED
    m = merge([Grid(a, RES, 0.0, 0.0), Grid(b, RES, 0.0, 0.0)])
    assert m.cells[0].tolist() == [FREE, OCCUPIED, OCCUPIED, UNKNOWN]
    assert (m.cells[1:] == UNKNOWN).all()


@pytest.mark.parametrize("shift", [(0.0, 0.0), (0.1, -0.05), (-0.15, 0.05)])
def test_agreement_finds_a_known_shift(shift: tuple[float, float]) -> None:
    a = Grid(_room(), RES, 1.0, 2.0)
    b = Grid(_room(), RES, 1.0 + shift[0], 2.0 + shift[1])
    ag = agreement(a, b)
    assert ag.shift_m is not None
    assert abs(ag.shift_m[0] - shift[0]) < 0.02 and abs(ag.shift_m[1] - shift[1]) < 0.02
    if shift == (0.0, 0.0):
        assert ag.agree == 1.0
    else:
        assert ag.agree is not None and ag.agree < 0.99


def test_report_and_picture() -> None:
    maps = {
        "r1": payloads.RobotMap("r1", 1, Grid(_room(), RES, 1.0, 2.0), ((2.0, 3.0), (3.0, 3.0))),
        "r2": payloads.RobotMap("r2", 1, Grid(_room()[:, :60], RES, 1.0, 2.0), ((4.0, 3.5),)),
    }
    poses = {"r1": PoseMessage(1, 3.0, 3.0, 0.3, 0.01, 0.01, 7)}
    out = report(maps, poses)
    (pair,) = out["pairs"]
    assert pair["robots"] == ["r1", "r2"] and pair["agreement"] == 1.0 and pair["shift_norm_m"] < 0.01
    img = picture(maps, poses)
    assert img.ndim == 3 and img.shape[0] > 400
    # r1's colour (its disc) is on the picture
    assert (np.abs(img.astype(int) - np.array((200, 80, 0))).sum(axis=2) == 0).any()


def test_fleet_loop_hands_its_map_to_the_bridge(tmp_path: Path, fleet_threads: FleetThreads) -> None:
    sock = tmp_path / "fleet.sock"
    pixels = np.full((60, 80), 205, np.uint8)
    pixels[10:50, 10:70] = 254
    pixels[10, 10:70] = 0
    image = OccupancyImage(pixels, RES, (1.0, 2.0, 0.0))
    geo = {"type": "FeatureCollection", "features": []}
    fleet_threads.agent(sock, topology=lambda: geo).loop.on_map(image)
    session = fleet_threads.bridge(sock).session
    got = payloads.decode_map(session.wait_for("fleet/r1/map"), "r1")
    assert np.array_equal(got.grid.cells, grid_from_image(pixels, RES, (1.0, 2.0)).cells)
    assert got.grid.origin_x_m == 1.0 and got.grid.origin_y_m == 2.0
    assert payloads.decode_topology(session.wait_for("fleet/r1/topology"), "r1") == geo
    fleet_threads.close()
    # Everything the bridge published passes the privacy audit; a collector takes the map.
    collector = FleetMaps()
    for key, data in session.published:
        assert audit.check("fleet", key, data) is None, key
        kind = key.rsplit("/", 1)[-1]
        if kind in ("map", "pose", "topology"):
            collector.take(kind, "r1", data)
    assert set(collector.maps) == {"r1"} and "r1" in collector.poses


def test_audit_refuses_undocumented_keys_and_images() -> None:
    assert audit.check("fleet", "fleet/r1/camera", b"\xff\xd8\xff") is not None
    assert audit.check("fleet", "fleet/r1/map", b"\x89PNG\r\n") is not None
    assert audit.check("fleet", "other/r1/pose", b"{}") is not None


def test_audit_refuses_fields_beyond_the_schema() -> None:
    pose = payloads.encode_pose("r1", PoseMessage(5, 1.0, 2.0, 0.0, 0.01, 0.02, 1))
    assert audit.check("fleet", "fleet/r1/pose", pose) is None
    smuggled = json.loads(pose) | {"jpeg": base64.b64encode(b"\xff\xd8\xff\xe0").decode()}
    problem = audit.check("fleet", "fleet/r1/pose", json.dumps(smuggled).encode())
    assert problem is not None and "jpeg" in problem  # decode_pose alone would take it
    status = json.loads(payloads.encode_status("r1", None, {"published_pose": 3}))
    assert audit.check("fleet", "fleet/r1/status", json.dumps(status).encode()) is None
    status["counters"] = {"published_pose": 3, "x" * 200: 1}
    assert audit.check("fleet", "fleet/r1/status", json.dumps(status).encode()) is not None
