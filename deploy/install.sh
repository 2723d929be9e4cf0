#!/usr/bin/env bash
# Install the emdflow daemon as a systemd service on Debian / Raspberry Pi OS / Ubuntu
# (Raspberry Pi, Jetson, any OAK host).
#
#   sudo deploy/install.sh                 # PoCL (CPU OpenCL): from pip on x86_64, from Debian
#                                          # (pocl-opencl-icd) on ARM (Pi, Jetson); service enabled
#   sudo deploy/install.sh --opencl apt    # Debian's PoCL on any processor
#   sudo deploy/install.sh --opencl vendor # the board's own OpenCL ICD (e.g. Mali; NVIDIA ships
#                                          # no OpenCL for Jetson: use the default PoCL there)
#   sudo deploy/install.sh --python python3.11   # Ubuntu 22.04 / Jetson JetPack 6 (python3 is 3.10)
#   deploy/install.sh --dry-run            # print every step, change nothing (no root needed)
#
# Steps: Python >= 3.11 check -> apt packages (python3-venv, binutils for PoCL's linker, the
# OpenCL ICD loader and driver) -> system user 'emdflow' in groups video, dialout (and
# render where it exists) -> its
# state and cache directories (home, PoCL kernel cache) -> venv in PREFIX with the package
# -> /etc/emdflow/emdflow.toml (kept if present) -> udev rule -> systemd unit.
set -euo pipefail

PREFIX=/opt/emdflow
CONF_DIR=/etc/emdflow
UNIT_DIR=/etc/systemd/system
UDEV_DIR=/etc/udev/rules.d
SERVICE_USER=emdflow
# The unit's StateDirectory=emdflow, CacheDirectory=emdflow and Environment= values. They
# are created here too: systemd makes them only when the service first starts, and the
# engine check (emdflowd --demo as the service user) comes before that.
STATE_DIR=/var/lib/emdflow
CACHE_DIR=/var/cache/emdflow
POCL_CACHE_DIR="$CACHE_DIR/pocl"
PYTHON=python3      # interpreter of the venv: Python >= 3.11 (tomllib)
OPENCL=             # pip | apt | vendor; default: pip on x86_64, apt elsewhere (below)
DEPTHAI=0
START=0
DRY_RUN=0
SRC="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"

usage() {
    # the header comment, up to the first line that is not one
    sed -n '2,/^[^#]/{/^#/s/^# \{0,1\}//p}' "${BASH_SOURCE[0]}"
    cat <<EOF

Options:
  --dry-run            print the commands instead of running them
  --prefix DIR         install the venv into DIR/venv (default $PREFIX)
  --user NAME          service user (default $SERVICE_USER)
  --opencl pip|apt|vendor
                       pip: pyopencl + PyPI's PoCL wheel (x86_64 only); apt: Debian's
                       pocl-opencl-icd; vendor: keep the board's ICD (default: pip on
                       x86_64, apt on other processors)
  --depthai            also install depthai (Luxonis OAK cameras)
  --python PY          interpreter for the venv, Python >= 3.11 (default $PYTHON); a name
                       like python3.11 is installed with apt too (with PY-venv)
  --start              start the service at the end (default: enable only)
  --source DIR         project checkout to install from (default $SRC)
  --udev-dir DIR       where the udev rule goes (default $UDEV_DIR)
EOF
}

value() {
    # The value of option $1, given as $2: missing, or another option, is a usage error
    # (`--prefix --dry-run` would otherwise install for real into a folder "--dry-run").
    if [ $# -lt 2 ] || [ -z "$2" ] || [ "${2#-}" != "$2" ]; then
        echo "install.sh: $1 needs a value (see --help)" >&2
        exit 2
    fi
    printf '%s' "$2"
}

while [ $# -gt 0 ]; do
    case "$1" in
        --dry-run) DRY_RUN=1 ;;
        --prefix) PREFIX="$(value "$@")"; shift ;;
        --user) SERVICE_USER="$(value "$@")"; shift ;;
        --opencl) OPENCL="$(value "$@")"; shift ;;
        --depthai) DEPTHAI=1 ;;
        --python) PYTHON="$(value "$@")"; shift ;;
        --start) START=1 ;;
        --source) SRC="$(value "$@")"; shift ;;
        --udev-dir) UDEV_DIR="$(value "$@")"; shift ;;
        -h|--help) usage; exit 0 ;;
        *) echo "install.sh: unknown option '$1' (see --help)" >&2; exit 2 ;;
    esac
    shift
done
for dir in "$PREFIX" "$UDEV_DIR"; do
    # (the unit's ExecStart= must be an absolute path, and the rule's folder is the system's)
    case "$dir" in /*) ;; *) echo "install.sh: $dir: give an absolute path (--prefix, --udev-dir)" >&2; exit 2 ;; esac
done
# The prefix goes into the unit's ExecStart= through sed (which reads & # \ in it) and systemd
# (which splits at whitespace, expands % and $, and parses quotes): refused, not written broken.
case "$PREFIX" in
    *[[:space:]\&\#\\%\$\"\']*)
        echo "install.sh: --prefix '$PREFIX': the unit's ExecStart= cannot hold whitespace or any of" \
            "& # \\ % \$ \" ' in the path: choose another folder" >&2
        exit 2 ;;
esac
# the service user goes into the unit's User= and Group= the same way: a name as useradd
# takes one (letters, digits, _ . -, not starting with -)
case "$SERVICE_USER" in
    ''|-*|*[!A-Za-z0-9_.-]*)
        echo "install.sh: --user '$SERVICE_USER': expected a user name of letters, digits, _ . -" >&2
        exit 2 ;;
esac
# PyPI's PoCL (pocl-binary-distribution) is one x86_64 wheel: on a Pi or a Jetson (aarch64)
# pip cannot install it, and the install stopped at step 4 with the user already made.
ARCH="$(uname -m)"
if [ -z "$OPENCL" ]; then
    if [ "$ARCH" = x86_64 ]; then OPENCL=pip; else OPENCL=apt; fi
elif [ "$OPENCL" = pip ] && [ "$ARCH" != x86_64 ]; then
    echo "install.sh: --opencl pip: PyPI's PoCL wheel is built for x86_64 only, this is $ARCH;" \
        "use --opencl apt (Debian's pocl-opencl-icd, the default here) or --opencl vendor" >&2
    exit 2
fi
case "$OPENCL" in pip|apt|vendor) ;; *) echo "install.sh: --opencl must be pip, apt or vendor" >&2; exit 2 ;; esac
[ -f "$SRC/pyproject.toml" ] || { echo "install.sh: $SRC is not an emdflow checkout (no pyproject.toml)" >&2; exit 2; }

run() {
    # Print, then run unless --dry-run.
    printf '+ %s\n' "$*"
    [ "$DRY_RUN" = 1 ] || "$@"
}

if [ "$DRY_RUN" = 0 ] && [ "$(id -u)" != 0 ]; then
    echo "install.sh: run as root (sudo), or with --dry-run to see the steps" >&2
    exit 1
fi

check_python() {
    # emdflow reads its configuration with tomllib: Python 3.11 or newer.
    local version status=0
    version="$("$PYTHON" -c 'import sys; print("%d.%d.%d" % sys.version_info[:3]); sys.exit(sys.version_info < (3, 11))' \
        2>/dev/null)" || status=$?
    if [ -z "$version" ]; then
        echo "install.sh: cannot run '$PYTHON' (--python); emdflow needs Python >= 3.11. Nothing was changed." >&2
        exit 1
    fi
    if [ "$status" != 0 ]; then
        cat >&2 <<EOF
install.sh: '$PYTHON' is Python $version; emdflow needs Python >= 3.11 (tomllib). Nothing was changed.
  Debian 12, Raspberry Pi OS bookworm and Ubuntu 24.04 have it as python3. Ubuntu 22.04
  (Jetson JetPack 6) has python3.10: use --python python3.11 (installed with apt, with
  python3.11-venv). Otherwise install a newer Python and pass --python /path/to/python3.X.
EOF
        exit 1
    fi
    echo "   $PYTHON is Python $version"
}

VENV="$PREFIX/venv"
APT_PKGS=(python3 python3-venv python3-pip binutils ocl-icd-libopencl1 clinfo)
case "$PYTHON" in
    python3) ;;
    python3.[0-9]*) APT_PKGS+=("$PYTHON" "$PYTHON-venv") ;;   # e.g. python3.11 on Ubuntu 22.04
    *) ;;                                                     # a path: the user installed it
esac
EXTRAS=opencl
case "$OPENCL" in
    pip) EXTRAS=pocl ;;                       # pyopencl[pocl]: PoCL wheels, needs binutils' ld
    apt) APT_PKGS+=(pocl-opencl-icd) ;;        # Debian's PoCL, found through /etc/OpenCL/vendors
    vendor) ;;                                 # e.g. Mali (libmali: see the unit's DeviceAllow), Rusticl
esac
[ "$DEPTHAI" = 1 ] && EXTRAS="$EXTRAS,depthai"

echo "== 0/7 Python >= 3.11 ($PYTHON)"
PYTHON_CHECKED=0
if command -v "$PYTHON" >/dev/null 2>&1 || [[ "$PYTHON" == */* ]]; then
    check_python        # before anything is installed or created (apt cannot supply a path)
    PYTHON_CHECKED=1
else
    echo "   $PYTHON is not installed yet: checked after the system packages"
fi

echo "== 1/7 system packages (OpenCL: $OPENCL, for $ARCH)"
run apt-get update
run apt-get install -y --no-install-recommends "${APT_PKGS[@]}"
if [ "$PYTHON_CHECKED" = 0 ] && [ "$DRY_RUN" = 0 ]; then
    check_python        # still before the user and the venv
fi

# Group 'render' (where it exists) owns /dev/dri/renderD*, which a GPU OpenCL driver opens.
GROUPS_LIST=video,dialout
if getent group render >/dev/null 2>&1; then GROUPS_LIST="$GROUPS_LIST,render"; fi
echo "== 2/7 service user '$SERVICE_USER' (groups ${GROUPS_LIST//,/, })"
if id "$SERVICE_USER" >/dev/null 2>&1; then
    run usermod -a -G "$GROUPS_LIST" "$SERVICE_USER"
else
    run useradd --system --user-group --home-dir "$STATE_DIR" --no-create-home --shell /usr/sbin/nologin \
        --groups "$GROUPS_LIST" "$SERVICE_USER"
fi

echo "== 3/7 state and cache directories $STATE_DIR, $CACHE_DIR (owner $SERVICE_USER)"
# The service user's home and PoCL's kernel cache must exist and be writable before the
# first 'emdflowd --demo' as that user: without them PoCL finds no usable device.
run install -d -o "$SERVICE_USER" -g "$SERVICE_USER" -m 0755 "$STATE_DIR" "$CACHE_DIR"
run install -d -o "$SERVICE_USER" -g "$SERVICE_USER" -m 0750 "$POCL_CACHE_DIR"

echo "== 4/7 Python venv in $VENV"
run mkdir -p "$PREFIX"
run "$PYTHON" -m venv "$VENV"
run "$VENV/bin/pip" install --upgrade pip
run "$VENV/bin/pip" install "$SRC[$EXTRAS]"
if [ "$OPENCL" = pip ]; then
    # pip's PoCL (3.0, LLVM 14) cannot compile for a processor newer than its LLVM ("unknown
    # target CPU 'generic'", e.g. AMD Zen 5). Debian's PoCL can; emdflow uses the first
    # OpenCL device that builds its kernels, so it is added only where pip's fails.
    # (`emdflow devices` builds the kernels and runs a frame on every device; exit 1: none works)
    printf '+ %s\n' "$VENV/bin/emdflow devices"
    if [ "$DRY_RUN" = 0 ]; then
        PROBE_CACHE="$(mktemp -d)"
        if ! PROBE_OUT=$(POCL_CACHE_DIR="$PROBE_CACHE" "$VENV/bin/emdflow" devices 2>&1); then
            WHY=$(printf '%s\n' "$PROBE_OUT" | grep -m1 'cannot run' || printf '%s\n' "$PROBE_OUT" | tail -n1)
            echo "   no OpenCL device runs the engine with pip's PoCL ($WHY): adding Debian's PoCL"
            run apt-get install -y --no-install-recommends pocl-opencl-icd
            if ! POCL_CACHE_DIR="$PROBE_CACHE" "$VENV/bin/emdflow" devices; then
                echo "   warning: still no OpenCL device runs the engine (above); 'emdflowd --demo' (step 2 below) says the same"
            fi
        else
            printf '%s\n' "$PROBE_OUT" | sed 's/^/   /'
        fi
        rm -rf "$PROBE_CACHE"
    fi
fi

echo "== 5/7 configuration $CONF_DIR/emdflow.toml"
run install -d -m 0755 "$CONF_DIR"
if [ -e "$CONF_DIR/emdflow.toml" ]; then
    echo "   keeping the existing $CONF_DIR/emdflow.toml (new example: $SRC/deploy/emdflow.toml)"
else
    run install -m 0644 "$SRC/deploy/emdflow.toml" "$CONF_DIR/emdflow.toml"
fi

echo "== 6/7 udev rule $UDEV_DIR/99-emdflow.rules (stable /dev/emdflow-camera, /dev/emdflow-fc)"
# The rule is meant to be edited (your camera's and adapter's IDs): one that differs from
# the example the last install shipped (kept beside it as .example) is yours and stays, like
# the configuration; an unedited one is updated.
RULE="$UDEV_DIR/99-emdflow.rules"
if [ -e "$RULE" ] && ! cmp -s "$SRC/deploy/99-emdflow.rules" "$RULE" \
        && ! { [ -e "$RULE.example" ] && cmp -s "$RULE.example" "$RULE"; }; then
    echo "   keeping $RULE: it differs from the example shipped (the new one: $RULE.example)"
else
    run install -m 0644 "$SRC/deploy/99-emdflow.rules" "$RULE"
fi
run install -m 0644 "$SRC/deploy/99-emdflow.rules" "$RULE.example"
run udevadm control --reload-rules
run udevadm trigger

echo "== 7/7 systemd unit $UNIT_DIR/emdflowd.service"
UNIT_TMP="$(mktemp)"
trap 'rm -f "$UNIT_TMP"' EXIT
sed -e "s#^ExecStart=.*#ExecStart=$VENV/bin/emdflowd --config $CONF_DIR/emdflow.toml#" \
    -e "s#^User=.*#User=$SERVICE_USER#" -e "s#^Group=.*#Group=$SERVICE_USER#" \
    "$SRC/deploy/emdflowd.service" >"$UNIT_TMP"
run install -m 0644 "$UNIT_TMP" "$UNIT_DIR/emdflowd.service"
if command -v systemd-analyze >/dev/null 2>&1; then
    # (--man=no: on an image without man pages the unit's Documentation=man:... link
    # failed the check, and set -e ended the install before enabling the service)
    run systemd-analyze verify --man=no "$UNIT_DIR/emdflowd.service"
fi
run systemctl daemon-reload
run systemctl enable emdflowd.service
[ "$START" = 1 ] && run systemctl restart emdflowd.service

cat <<EOF

Done. Next:
  1. edit $CONF_DIR/emdflow.toml: [source] uri, [optics] focal_length_px, [link] port/baud/autopilot
  2. check the engine as the service user, in the unit's environment:
       sudo -u $SERVICE_USER env HOME=$STATE_DIR XDG_CACHE_HOME=$CACHE_DIR POCL_CACHE_DIR=$POCL_CACHE_DIR $VENV/bin/emdflowd --demo
  3. start the service:  sudo systemctl start emdflowd
  4. watch it:           journalctl -u emdflowd -f     (status line with latency p50/p99)
EOF
