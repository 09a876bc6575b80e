#!/usr/bin/env bash
# Install vlp-agent as a systemd service on the robot, or remove it again. `install.sh --help` says how;
# docs/operations.md says what to do next (config, logs, watchdog, device names, permissions).
set -euo pipefail

readonly PROG="${0##*/}"
SCRIPT_DIR="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
REPO_DIR="$(dirname "$SCRIPT_DIR")"
readonly SCRIPT_DIR REPO_DIR

# Where things go. PREFIX is fixed because the unit's ExecStart= names it.
readonly SERVICE=vlp-agent.service
# The fleet bridge (docs/fleet.md): installed beside the agent, never enabled by this script (a robot joins a
# fleet when someone writes /etc/vlp-agent/bridge.toml and enables it).
readonly BRIDGE_SERVICE=vlp-agent-bridge.service
readonly USER_NAME=vlp-agent
readonly PREFIX=/opt/vlp-agent
readonly VENV="$PREFIX/venv"
readonly MANIFEST="$PREFIX/install-manifest"
readonly DOC="$PREFIX/share/doc/operations.md"
readonly RULES=/etc/udev/rules.d/99-vlp-agent.rules
readonly CONFIG_DIR=/etc/vlp-agent
readonly CONFIG="$CONFIG_DIR/robot.toml"
readonly STATE_DIR=/var/lib/vlp-agent
readonly LOGS_DIR=/var/log/vlp-agent
# The unit's SupplementaryGroups=: a group that does not exist makes the service fail with 216/GROUP.
readonly DEVICE_GROUPS=(dialout video i2c plugdev)

# Temporary directories to remove on exit.
declare -a cleanup=()
trap 'rm -rf -- "${cleanup[@]}"' EXIT

usage() {
    cat <<EOF
Usage: $PROG [--wheel FILE] [--no-venv] [--unit-dir DIR] [--no-enable]
       $PROG --uninstall [--purge]

Installs vlp-agent as a systemd service (run as root):
  - the system user and group '$USER_NAME' (and any of the groups ${DEVICE_GROUPS[*]} that are missing),
  - a virtual environment in $VENV with the package from this checkout ($REPO_DIR)
    or from --wheel FILE,
  - the unit $SERVICE in /etc/systemd/system (or --unit-dir), the udev rules $RULES,
  - the fleet bridge's unit $BRIDGE_SERVICE beside it, disabled: to join a fleet, write
    $CONFIG_DIR/bridge.toml, then 'systemctl enable --now $BRIDGE_SERVICE' (docs/fleet.md),
  - a config $CONFIG if there is none (examples/turtlebot3.toml when the checkout has it),
  - then reloads systemd and udev, enables the service and restarts it if it was running.
Running it again upgrades in place; an existing config is never overwritten.

Options:
  --wheel FILE    install this wheel instead of the checkout
  --no-venv       do not create the venv or install the package (the service cannot start without them)
  --unit-dir DIR  where the unit goes (default /etc/systemd/system; /lib/systemd/system for images)
  --no-enable     install, but do not enable or restart the service
  --uninstall     remove what the install put down (listed in $MANIFEST): the service is stopped and
                  disabled; the state in $STATE_DIR, the user and an edited config are kept
  --purge         with --uninstall: also remove $STATE_DIR, $LOGS_DIR, $CONFIG_DIR and the
                  user and groups the install created
  -h, --help      this text

Environment:
  DESTDIR   install into this directory instead of / (for tests and image builds). Nothing on the running
            system is touched: the useradd/groupadd/systemctl/udevadm commands are printed, not run. The
            venv is created inside DESTDIR (its scripts then point into DESTDIR: use it for tests only).
  PYTHON    the Python (>= 3.11) for the venv (default: python3)
  PIP_*     passed to pip as usual (PIP_INDEX_URL, PIP_FIND_LINKS, PIP_NO_INDEX for offline installs)
EOF
}

die() {
    printf '%s: %s\n' "$PROG" "$*" >&2
    exit 1
}

note() {
    printf '%s\n' "$*"
}

# A command that changes the running system (users, systemd, udev): run it, or under DESTDIR only say it.
host() {
    if [[ -n "$DESTDIR" ]]; then
        printf 'would run:'
        printf ' %q' "$@"
        printf '\n'
    else
        printf '+'
        printf ' %q' "$@"
        printf '\n'
        "$@"
    fi
}

# Like host, for commands whose failure must not stop the script (udevd or systemd not running: a chroot).
host_try() {
    host "$@" || note "warning: '$*' failed; continuing"
}

systemd_running() {
    [[ -z "$DESTDIR" && -d /run/systemd/system ]]
}

# --- arguments ---------------------------------------------------------------------------------------------
mode=install
wheel=""
make_venv=1
enable=1
purge=0
unit_dir=/etc/systemd/system
while (($#)); do
    case "$1" in
        --wheel)
            (($# >= 2)) || die "--wheel needs a file"
            wheel="$2"
            shift
            ;;
        --no-venv) make_venv=0 ;;
        --unit-dir)
            (($# >= 2)) || die "--unit-dir needs a directory"
            unit_dir="$2"
            shift
            ;;
        --no-enable) enable=0 ;;
        --uninstall) mode=uninstall ;;
        --purge) purge=1 ;;
        -h | --help)
            usage
            exit 0
            ;;
        *) die "unknown argument '$1' (see --help)" ;;
    esac
    shift
done
((purge == 0)) || [[ "$mode" == uninstall ]] || die "--purge only goes with --uninstall"
[[ -z "$wheel" || "$make_venv" == 1 ]] || die "--wheel and --no-venv contradict each other"
[[ "$unit_dir" == /* ]] || die "--unit-dir must be absolute, not '$unit_dir'"
unit_dir="${unit_dir%/}"

DESTDIR="${DESTDIR:-}"
if [[ -n "$DESTDIR" ]]; then
    [[ "$DESTDIR" != / ]] || die "DESTDIR=/ : unset DESTDIR to install on this system"
    mkdir -p "$DESTDIR"
    DESTDIR="$(cd "$DESTDIR" && pwd)"
elif ((EUID != 0)); then
    die "run as root (or set DESTDIR to install into a directory)"
fi
readonly DESTDIR

# --- manifest: what this script created, so that --uninstall removes exactly that ---------------------------
# One record per line: "file PATH", "dir PATH", "config PATH SHA256", "user NAME", "group NAME". Each record
# is appended as soon as the thing exists, so an interrupted install can still be uninstalled; records from
# earlier runs stay (a user or a config created then is still ours to remove).
declare -a pending=()

record() {
    pending+=("$*")
    [[ -d "$DESTDIR$PREFIX" ]] || return 0 # the manifest's directory comes first; until then, hold on
    local line target="$DESTDIR$MANIFEST"
    for line in "${pending[@]}"; do
        grep -qxF -- "$line" "$target" 2>/dev/null || printf '%s\n' "$line" >>"$target"
    done
    pending=()
}

sha256() {
    sha256sum "$1" | cut -d' ' -f1
}

# --- install ------------------------------------------------------------------------------------------------
make_dirs() { # PATH: create it and its missing parents (under DESTDIR), recording each one created
    local path="$1" missing=()
    while [[ "$path" != / && ! -d "$DESTDIR$path" ]]; do
        missing=("$path" "${missing[@]}")
        path="$(dirname "$path")"
    done
    for path in "${missing[@]}"; do
        mkdir -m 0755 "$DESTDIR$path"
        record dir "$path"
    done
}

install_file() { # SOURCE DEST MODE
    local dest="$DESTDIR$2"
    make_dirs "$(dirname "$2")"
    install -m "$3" "$1" "$dest"
    record file "$2"
    note "installed $2"
}

ensure_accounts() {
    local group
    local -a useradd=(useradd --system --user-group --home-dir "$STATE_DIR" --no-create-home
        --shell /usr/sbin/nologin --comment "vlp-agent service" "$USER_NAME")
    for group in "${DEVICE_GROUPS[@]}"; do
        if [[ -n "$DESTDIR" ]]; then
            note "would run: getent group $group >/dev/null || groupadd --system $group"
        elif ! getent group "$group" >/dev/null; then
            host groupadd --system "$group"
            record group "$group"
        fi
    done
    if [[ -n "$DESTDIR" ]]; then
        note "would run: getent passwd $USER_NAME >/dev/null ||$(printf ' %q' "${useradd[@]}")"
    elif ! getent passwd "$USER_NAME" >/dev/null; then
        host "${useradd[@]}"
        record user "$USER_NAME"
    fi
}

install_venv() {
    local venv="$DESTDIR$VENV" source
    command -v "$PYTHON" >/dev/null || die "no '$PYTHON' (set PYTHON to a Python >= 3.11)"
    "$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 11))' ||
        die "$PYTHON is $("$PYTHON" -V 2>&1); vlp-agent needs Python >= 3.11 (set PYTHON)"
    if [[ ! -x "$venv/bin/python" ]]; then
        "$PYTHON" -m venv "$venv" || die "could not create $venv (on Debian: apt-get install python3-venv)"
        note "created venv $VENV"
    fi
    if [[ -n "$wheel" ]]; then
        [[ -f "$wheel" ]] || die "no wheel at '$wheel'"
        source="$(cd "$(dirname "$wheel")" && pwd)/$(basename "$wheel")"
    else
        [[ -f "$REPO_DIR/pyproject.toml" ]] || die "no pyproject.toml in $REPO_DIR: pass --wheel FILE"
        # pip builds a local project in place, leaving build/ in the checkout, and setuptools then packages
        # whatever stale modules build/lib still holds. Build from a clean copy instead.
        source="$(mktemp -d)/vlp-agent"
        mkdir "$source"
        tar -C "$REPO_DIR" --exclude=./.git --exclude=./.venv --exclude=./build --exclude=./dist \
            --exclude='*.egg-info' --exclude=__pycache__ --exclude='.*_cache' --exclude=./.hypothesis \
            -cf - . | tar -C "$source" -xf -
        cleanup+=("$(dirname "$source")")
    fi
    # --upgrade: a re-run with a newer checkout or wheel replaces the installed version.
    "$venv/bin/python" -m pip install --quiet --disable-pip-version-check --upgrade "$source"
    [[ -x "$venv/bin/vlp-agent" ]] || die "pip finished but $VENV/bin/vlp-agent is missing"
    note "installed $("$venv/bin/vlp-agent" --version) from ${wheel:-$REPO_DIR} into $VENV"
}

install_config() {
    local dest="$DESTDIR$CONFIG" example="$REPO_DIR/examples/turtlebot3.toml"
    make_dirs "$CONFIG_DIR"
    if [[ -e "$dest" ]]; then
        note "kept the existing $CONFIG"
        return
    fi
    if [[ -f "$example" ]]; then
        install -m 0644 "$example" "$dest"
        note "installed $CONFIG from examples/turtlebot3.toml: edit it for this robot"
    else
        cat >"$dest" <<'EOF'
# vlp-agent configuration for this robot: PLACEHOLDER.
#
# systemd/install.sh wrote this file because the checkout it ran from had no examples/turtlebot3.toml.
# Describe the robot's devices here (keys and examples: docs/config.md in the vlp-agent repository), then
# `systemctl restart vlp-agent`. Until then the service will not start.
EOF
        chmod 0644 "$dest"
        note "wrote a placeholder $CONFIG: fill it in (docs/config.md) before starting the service"
    fi
    record config "$CONFIG" "$(sha256 "$dest")"
}

do_install() {
    local unit_src="$SCRIPT_DIR/$SERVICE" rules_src="$SCRIPT_DIR/99-vlp-agent.rules"
    local bridge_src="$SCRIPT_DIR/$BRIDGE_SERVICE"
    [[ -f "$unit_src" && -f "$rules_src" && -f "$bridge_src" ]] ||
        die "$unit_src, $bridge_src or $rules_src is missing"
    PYTHON="${PYTHON:-python3}"

    make_dirs "$PREFIX"
    ensure_accounts
    if ((make_venv)); then
        install_venv
    else
        note "skipped the venv and the package (--no-venv)"
    fi
    if [[ -f "$REPO_DIR/docs/operations.md" ]]; then
        install_file "$REPO_DIR/docs/operations.md" "$DOC" 0644
    fi
    install_file "$unit_src" "$unit_dir/$SERVICE" 0644
    install_file "$bridge_src" "$unit_dir/$BRIDGE_SERVICE" 0644 # not enabled: see --help
    install_file "$rules_src" "$RULES" 0644
    install_config

    # udev first: the rules name groups (i2c, vlp-agent) that may have just been created.
    if [[ -n "$DESTDIR" ]] || command -v udevadm >/dev/null; then
        host_try udevadm control --reload-rules
        host_try udevadm trigger --action=add --subsystem-match=tty --subsystem-match=usb \
            --subsystem-match=i2c-dev --subsystem-match=misc
    else
        note "warning: udevadm not found: the rules apply from the next boot"
    fi
    if systemd_running || [[ -n "$DESTDIR" ]]; then
        host systemctl daemon-reload
    fi
    if ((enable)); then
        host systemctl enable "$SERVICE"
        # An upgrade takes effect now if the agent was running; a stopped agent stays stopped.
        if systemd_running || [[ -n "$DESTDIR" ]]; then
            host systemctl try-restart "$SERVICE"
        fi
    fi
    if [[ -z "$DESTDIR" && ! -x "$VENV/bin/vlp-agent" ]]; then
        note "warning: $VENV/bin/vlp-agent does not exist: the service cannot start until it does"
    fi
    note "done. Next: edit $CONFIG, then 'systemctl start vlp-agent' and 'journalctl -u vlp-agent -f'" \
        "(docs/operations.md)."
}

# --- uninstall ----------------------------------------------------------------------------------------------
remove_path() { # PATH (under DESTDIR)
    local path="$DESTDIR$1"
    if [[ -e "$path" || -L "$path" ]]; then
        rm -rf -- "$path"
        note "removed $1"
    fi
}

do_uninstall() {
    local manifest="$DESTDIR$MANIFEST" line kind path sha current
    local -a lines=() users=() groups=() dirs=()
    if [[ -f "$manifest" ]]; then
        mapfile -t lines <"$manifest"
    else
        note "no $MANIFEST: removing the default install locations"
        lines=("file /etc/systemd/system/$SERVICE" "file /lib/systemd/system/$SERVICE" "file $RULES"
            "file /etc/systemd/system/$BRIDGE_SERVICE" "file /lib/systemd/system/$BRIDGE_SERVICE"
            "file $DOC" "dir $PREFIX")
    fi

    local unit_present=0 bridge_present=0
    for line in "${lines[@]}"; do
        read -r kind path sha <<<"$line"
        [[ "$kind" != file || "$path" != */"$SERVICE" || ! -e "$DESTDIR$path" ]] || unit_present=1
        [[ "$kind" != file || "$path" != */"$BRIDGE_SERVICE" || ! -e "$DESTDIR$path" ]] || bridge_present=1
    done
    # The bridge first (it serves the agent's socket); enabled or not, it is stopped and disabled.
    if ((bridge_present == 0)); then
        :
    elif systemd_running || [[ -n "$DESTDIR" ]]; then
        host_try systemctl disable --now "$BRIDGE_SERVICE"
    elif command -v systemctl >/dev/null; then
        host_try systemctl disable "$BRIDGE_SERVICE"
    fi
    if ((unit_present == 0)); then
        : # nothing to stop or disable (already uninstalled, or never installed)
    elif systemd_running || [[ -n "$DESTDIR" ]]; then
        host_try systemctl disable --now "$SERVICE"
    elif command -v systemctl >/dev/null; then
        host_try systemctl disable "$SERVICE" # no systemd running (a chroot): drop the enablement link only
    fi

    for line in "${lines[@]}"; do
        read -r kind path sha <<<"$line"
        case "$kind" in
            file) remove_path "$path" ;;
            dir) dirs+=("$path") ;;
            user) users+=("$path") ;;
            group) groups+=("$path") ;;
            config)
                [[ -e "$DESTDIR$path" ]] || continue
                current="$(sha256 "$DESTDIR$path")"
                if ((purge)) || [[ "$current" == "$sha" ]]; then
                    remove_path "$path"
                else
                    note "kept $path: it was edited after the install (--purge removes it)"
                fi
                ;;
            *) note "warning: ignoring manifest line '$line'" ;;
        esac
    done
    remove_path "$VENV"

    # Without --purge the user (and any group made for it) stays, because it owns the kept state. Its
    # records stay too, in a root-owned manifest, so that a later --purge still knows they are ours.
    local keep_accounts=0
    if ((purge == 0 && ${#users[@]} + ${#groups[@]} > 0)); then
        keep_accounts=1
    fi
    if ((keep_accounts)); then
        {
            printf 'dir %s\n' "${dirs[@]}"
            printf 'user %s\n' "${users[@]}"
            printf 'group %s\n' "${groups[@]}"
        } | grep -v ' $' >"$DESTDIR$MANIFEST.new"
        mv -f "$DESTDIR$MANIFEST.new" "$DESTDIR$MANIFEST"
        note "kept $MANIFEST: it lists the accounts that --uninstall --purge removes"
    else
        remove_path "$MANIFEST"
    fi
    # Deepest first; a directory that holds anything not ours stays (rmdir fails on it, quietly).
    while read -r path; do
        [[ -n "$path" ]] || continue
        if [[ "$path" == "$PREFIX" ]]; then
            # Only ours inside: the venv, the docs, the manifest.
            ((keep_accounts)) || remove_path "$PREFIX"
        elif [[ -d "$DESTDIR$path" ]] && rmdir -- "$DESTDIR$path" 2>/dev/null; then
            note "removed $path"
        fi
    done < <(((${#dirs[@]})) && printf '%s\n' "${dirs[@]}" | awk -F/ '{ print NF "\t" $0 }' | sort -rn |
        cut -f2-)
    local unit
    for unit in "$SERVICE" "$BRIDGE_SERVICE"; do
        if [[ -d "$DESTDIR/etc/systemd/system/$unit.d" ]]; then
            note "kept /etc/systemd/system/$unit.d: local drop-ins are not the install's to remove"
        fi
    done

    if ((purge)); then
        remove_path "$STATE_DIR"
        remove_path "$LOGS_DIR"
        remove_path "$CONFIG_DIR"
        for path in "${users[@]}"; do
            host_try userdel "$path"
        done
        for path in "${groups[@]}"; do
            host_try groupdel "$path"
        done
    else
        [[ ! -d "$DESTDIR$STATE_DIR" ]] || note "kept $STATE_DIR (maps, calibration; --purge removes it)"
        ((${#users[@]} == 0)) || note "kept the user ${users[*]}, which owns $STATE_DIR (--purge removes it)"
    fi

    if systemd_running || [[ -n "$DESTDIR" ]]; then
        host systemctl daemon-reload
    fi
    if [[ -n "$DESTDIR" ]] || command -v udevadm >/dev/null; then
        host_try udevadm control --reload-rules
    fi
    note "uninstalled."
}

if [[ "$mode" == install ]]; then
    do_install
else
    do_uninstall
fi
