"""The systemd unit and udev rules say what the robot needs, and agree with each other and with install.sh.

Static checks on the text; the real tools run through ``.ci/systemd-checks`` (``systemd-analyze verify``
and ``security``) when systemd-analyze is installed, and are skipped otherwise.
"""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
from collections import defaultdict
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
UNIT = REPO / "systemd" / "vlp-agent.service"
RULES = REPO / "systemd" / "99-vlp-agent.rules"
INSTALL = REPO / "systemd" / "install.sh"
CHECKS = REPO / ".ci" / "systemd-checks"

Unit = dict[str, dict[str, list[str]]]


def parse_unit(text: str) -> Unit:
    """Section -> key -> every value assigned, in order (systemd keys may repeat, e.g. DeviceAllow=)."""
    unit: Unit = defaultdict(lambda: defaultdict(list))
    section = None
    for number, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line or line[0] in "#;":
            continue
        assert not line.endswith("\\"), f"line {number}: continuation lines are not used here"
        if line.startswith("[") and line.endswith("]"):
            section = line[1:-1]
            continue
        assert section is not None, f"line {number}: a key before any section"
        key, sep, value = line.partition("=")
        assert sep, f"line {number}: not KEY=value: {raw!r}"
        unit[section][key.strip()].append(value.strip())
    return unit


@pytest.fixture(scope="module")
def unit() -> Unit:
    return parse_unit(UNIT.read_text(encoding="utf-8"))


def one(unit: Unit, section: str, key: str) -> str:
    values = unit[section].get(key, [])
    assert len(values) == 1, f"[{section}] {key}= should be set exactly once, got {values}"
    return values[0]


def words(unit: Unit, section: str, key: str) -> list[str]:
    return [w for value in unit[section].get(key, []) for w in value.split()]


def seconds(value: str) -> float:
    match = re.fullmatch(r"(\d+(?:\.\d+)?)(ms|s|min)?", value)
    assert match, f"not a simple time span: {value!r}"
    return float(match.group(1)) * {"ms": 0.001, "s": 1.0, "min": 60.0, None: 1.0}[match.group(2)]


def install_sh_value(name: str) -> str:
    """A ``readonly NAME=value`` from install.sh, unquoted, with the ``$OTHER`` names in it expanded."""
    match = re.search(rf"^readonly {name}=(\(.*?\)|\S+)$", INSTALL.read_text(encoding="utf-8"), re.M)
    assert match, f"install.sh has no 'readonly {name}='"
    return re.sub(r"\$([A-Z_]+)", lambda m: install_sh_value(m.group(1)), match.group(1).strip('"'))


# -- the unit -------------------------------------------------------------------------------------------


def test_lifecycle_is_notify_with_watchdog_and_bounded_restarts(unit: Unit) -> None:
    assert one(unit, "Service", "Type") == "notify"
    assert one(unit, "Service", "NotifyAccess") == "main"
    assert 0 < seconds(one(unit, "Service", "WatchdogSec")) <= 60
    assert one(unit, "Service", "Restart") == "on-failure"
    assert seconds(one(unit, "Service", "RestartSec")) >= 1
    # Start limits live in [Unit] (in [Service] they are ignored with a warning, which CI would catch too).
    assert int(one(unit, "Unit", "StartLimitBurst")) >= 1
    assert seconds(one(unit, "Unit", "StartLimitIntervalSec")) > seconds(one(unit, "Service", "RestartSec"))
    assert seconds(one(unit, "Service", "TimeoutStartSec")) > 0
    assert one(unit, "Install", "WantedBy") == "multi-user.target"


def test_watchdog_kill_leaves_python_stacks_in_the_journal(unit: Unit) -> None:
    env = dict(item.split("=", 1) for item in words(unit, "Service", "Environment"))
    assert env.get("PYTHONFAULTHANDLER") == "1"  # the watchdog's SIGABRT then dumps every thread
    assert "WatchdogSignal" not in unit["Service"]  # SIGABRT, the default, is what the fault handler catches


def test_execstart_runs_the_venv_installed_by_install_sh(unit: Unit) -> None:
    argv = shlex.split(one(unit, "Service", "ExecStart"))
    assert argv == [
        install_sh_value("VENV") + "/bin/vlp-agent",
        "run",
        "--config",
        install_sh_value("CONFIG"),
    ]
    assert argv[0] == "/opt/vlp-agent/venv/bin/vlp-agent"
    assert argv[-1] == "/etc/vlp-agent/robot.toml"


def test_dedicated_user_with_the_device_groups_install_sh_creates(unit: Unit) -> None:
    assert one(unit, "Service", "User") == install_sh_value("USER_NAME") == "vlp-agent"
    assert one(unit, "Service", "Group") == "vlp-agent"
    groups = words(unit, "Service", "SupplementaryGroups")
    assert groups == ["dialout", "video", "i2c", "plugdev"]
    assert install_sh_value("DEVICE_GROUPS") == "(" + " ".join(groups) + ")"
    assert "DynamicUser" not in unit["Service"]


def test_directories(unit: Unit) -> None:
    assert set(words(unit, "Service", "StateDirectory")) >= {"vlp-agent/maps", "vlp-agent/calibration"}
    assert words(unit, "Service", "ConfigurationDirectory") == ["vlp-agent"]
    assert words(unit, "Service", "LogsDirectory") == ["vlp-agent"]
    assert words(unit, "Service", "RuntimeDirectory") == ["vlp-agent"]


def test_filesystem_and_privilege_hardening(unit: Unit) -> None:
    expected = {
        "NoNewPrivileges": "yes",
        "ProtectSystem": "strict",
        "ProtectHome": "yes",
        "PrivateTmp": "yes",
        "ProtectKernelTunables": "yes",
        "ProtectKernelModules": "yes",
        "ProtectKernelLogs": "yes",
        "ProtectControlGroups": "yes",
        "ProtectClock": "yes",
        "ProtectHostname": "yes",
        "RestrictNamespaces": "yes",
        "RestrictSUIDSGID": "yes",
        "LockPersonality": "yes",
        "SystemCallArchitectures": "native",
    }
    assert {key: one(unit, "Service", key) for key in expected} == expected
    assert one(unit, "Service", "CapabilityBoundingSet") == ""
    assert "@system-service" in words(unit, "Service", "SystemCallFilter")
    # Hardware access needs the real /dev: the allow-list below does the filtering instead.
    assert one(unit, "Service", "PrivateDevices") == "no"


def test_memory_deny_write_execute_is_off_and_says_why(unit: Unit) -> None:
    assert one(unit, "Service", "MemoryDenyWriteExecute") == "no"
    lines = UNIT.read_text(encoding="utf-8").splitlines()
    at = next(i for i, line in enumerate(lines) if line.startswith("MemoryDenyWriteExecute="))
    comment = " ".join(line for line in lines[max(0, at - 5) : at] if line.startswith("#"))
    assert "numpy" in comment and "OpenCV" in comment and "SDK" in comment


def test_no_network_at_all(unit: Unit) -> None:
    assert one(unit, "Service", "PrivateNetwork") == "yes"
    assert one(unit, "Service", "IPAddressDeny") == "any"
    assert "IPAddressAllow" not in unit["Service"]
    families = words(unit, "Service", "RestrictAddressFamilies")
    assert sorted(families) == ["AF_NETLINK", "AF_UNIX"]  # AF_UNIX: sd_notify and the journal


# Character device majors, fixed by the kernel (Documentation/admin-guide/devices.txt), and the names
# /proc/devices gives them.
DEVICE_MAJORS = {4: "ttyS", 166: "ttyACM", 188: "ttyUSB", 81: "video4linux", 89: "i2c", 189: "usb_device"}


def test_device_allow_list_is_closed_and_covers_serial_video_i2c_usb(unit: Unit) -> None:
    assert one(unit, "Service", "DevicePolicy") == "closed"
    allowed = {}
    paths = {}
    for value in unit["Service"]["DeviceAllow"]:
        spec, access = value.split()
        if spec.startswith("/dev/"):
            paths[spec] = access
            continue
        match = re.fullmatch(r"char-(\d+)", spec)
        assert match, f"DeviceAllow={value}: use the fixed major number (see the unit's comment)"
        allowed[int(match.group(1))] = access
    assert allowed == dict.fromkeys(DEVICE_MAJORS, "rw")
    # One node by path, write only: the CPU latency QoS request (a class would be all of misc).
    assert paths == {"/dev/cpu_dma_latency": "w"}


def test_device_majors_match_this_kernel_where_it_has_the_driver() -> None:
    proc = Path("/proc/devices")
    if not proc.exists():
        pytest.skip("no /proc/devices")
    char_section = proc.read_text().split("Block devices:")[0]
    majors_of: dict[str, set[int]] = defaultdict(set)
    for major, name in re.findall(r"^\s*(\d+)\s+(\S+)$", char_section, re.M):
        majors_of[name].add(int(major))
    # A driver that is not loaded here is not listed: only the ones that are can be compared.
    for major, name in DEVICE_MAJORS.items():
        if name in majors_of:
            assert majors_of[name] == {major}, (
                f"{name}: /proc/devices says {majors_of[name]}, the unit {major}"
            )


def test_every_directive_group_has_a_comment() -> None:
    # The unit is read by people deciding whether a sandbox setting can go: each block of directives
    # (lines between blank lines) in [Service] starts with a comment saying why.
    text = UNIT.read_text(encoding="utf-8").split("[Service]", 1)[1].split("[Install]", 1)[0]
    for block in re.split(r"\n\s*\n", text.strip()):
        first = block.strip().splitlines()[0]
        assert first.startswith("#"), f"directive block without a comment: {first!r}"


# -- the udev rules -------------------------------------------------------------------------------------

MATCH_KEYS = {
    "ACTION",
    "SUBSYSTEM",
    "SUBSYSTEMS",
    "KERNEL",
    "KERNELS",
    "DRIVER",
    "DRIVERS",
    "ATTR",
    "ATTRS",
    "ENV",
}
ASSIGN_KEYS = {"GROUP", "MODE", "OWNER", "SYMLINK", "TAG", "ENV", "ATTR", "GOTO", "LABEL"}
PAIR = re.compile(r'([A-Z_]+)(?:\{([^}]+)\})?(==|!=|\+=|-=|:=|=)"([^"]*)"')


def parse_rules(text: str) -> list[list[tuple[str, str | None, str, str]]]:
    """Rules as lists of (key, attribute, operator, value), checked against udev's syntax as we use it."""
    rules = []
    for number, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        pairs = []
        rest = line
        while rest:
            match = PAIR.match(rest)
            assert match, f"rules line {number}: cannot parse at {rest!r}"
            key, attr, op, value = match.groups()
            if op in ("==", "!="):
                assert key in MATCH_KEYS, f"rules line {number}: {key} is not a match key"
            else:
                assert key in ASSIGN_KEYS, f"rules line {number}: {key} cannot be assigned"
            pairs.append((key, attr, op, value))
            rest = rest[match.end() :]
            if rest:
                assert rest.startswith(", "), f"rules line {number}: expected ', ' before {rest!r}"
                rest = rest[2:]
        rules.append(pairs)
    return rules


@pytest.fixture(scope="module")
def rules() -> list[list[tuple[str, str | None, str, str]]]:
    return parse_rules(RULES.read_text(encoding="utf-8"))


def rule_for(
    rules: list[list[tuple[str, str | None, str, str]]], vendor: str, product: str | None
) -> dict[str, str]:
    """The rule matching a USB id, flattened to 'KEY{attr}op' -> value."""
    for rule in rules:
        flat = {f"{k}{{{a}}}{op}" if a else f"{k}{op}": v for k, a, op, v in rule}
        vendor_key = "ATTRS{idVendor}==" if "ATTRS{idVendor}==" in flat else "ATTR{idVendor}=="
        if flat.get(vendor_key) == vendor and (product is None or flat.get("ATTRS{idProduct}==") == product):
            return flat
    raise AssertionError(f"no rule for {vendor}:{product}")


@pytest.mark.parametrize(
    ("vendor", "product", "name", "kernel"),
    [
        ("15d1", "0000", "urg", "ttyACM[0-9]*"),
        ("0403", "6014", "dynamixel", "ttyUSB[0-9]*"),
        ("0483", "5740", "opencr", "ttyACM[0-9]*"),
    ],
)
def test_serial_devices_get_stable_names_and_device_units(
    rules: list[list[tuple[str, str | None, str, str]]], vendor: str, product: str, name: str, kernel: str
) -> None:
    rule = rule_for(rules, vendor, product)
    assert rule["SUBSYSTEM=="] == "tty"
    assert rule["KERNEL=="] == kernel
    assert rule["SYMLINK+="] == name
    assert rule["TAG+="] == "systemd"  # -> dev-<name>.device
    assert rule["GROUP="] == "dialout"
    assert rule["MODE="] == "0660"
    assert rule["ENV{ID_MM_DEVICE_IGNORE}="] == "1"


def test_u2d2_latency_timer_is_one_millisecond_with_sources_cited(
    rules: list[list[tuple[str, str | None, str, str]]],
) -> None:
    assert rule_for(rules, "0403", "6014")["ATTR{device/latency_timer}="] == "1"
    text = RULES.read_text(encoding="utf-8")
    assert "99-interbotix-udev.rules" in text
    assert "DynamixelSDK" in text and "port_handler_linux.cpp" in text


@pytest.mark.parametrize("vendor", ["f622", "080b"])
def test_mindvision_usb_node_goes_to_group_video(
    rules: list[list[tuple[str, str | None, str, str]]], vendor: str
) -> None:
    rule = rule_for(rules, vendor, None)
    assert rule["SUBSYSTEM=="] == "usb"
    assert rule["ENV{DEVTYPE}=="] == "usb_device"
    assert (rule["GROUP="], rule["MODE="]) == ("video", "0660")


def test_rules_only_use_the_services_groups_and_never_world_writable(
    unit: Unit, rules: list[list[tuple[str, str | None, str, str]]]
) -> None:
    groups = set(words(unit, "Service", "SupplementaryGroups")) | {one(unit, "Service", "Group")}
    for rule in rules:
        for key, _attr, _op, value in rule:
            if key == "GROUP":
                assert value in groups
            if key == "MODE":
                assert int(value, 8) & 0o007 == 0, f"MODE={value} lets every user at the device"


def test_rules_goto_has_its_label(rules: list[list[tuple[str, str | None, str, str]]]) -> None:
    gotos = {v for rule in rules for k, _a, _o, v in rule if k == "GOTO"}
    labels = {v for rule in rules for k, _a, _o, v in rule if k == "LABEL"}
    assert gotos and gotos <= labels


def test_rules_parser_rejects_what_udev_would_reject() -> None:
    for bad in [
        'KERNEL="ttyACM0", SYMLINK+="x"',
        'SYMLINK=="x"',
        'ATTRS{idVendor}=="15d1",SYMLINK+="x"',
        "GROUP=dialout",
    ]:
        with pytest.raises(AssertionError):
            parse_rules(bad)


# -- the real tools --------------------------------------------------------------------------------------


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze is not installed")
def test_ci_systemd_checks_pass() -> None:
    result = subprocess.run([str(CHECKS), "--no-install"], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "ok: systemd-analyze verify: rc 0, no stderr" in result.stdout
    exposure = re.search(r"ok: exposure (\d+\.\d+) <= 2\.0", result.stdout)
    assert exposure, result.stdout
