#!/usr/bin/env bash
# Install the emdflow daemon as a systemd service on Debian / Raspberry Pi OS / Ubuntu
# (Raspberry Pi, Jetson, any OAK host).
#
#   sudo deploy/install.sh                 # PoCL (CPU OpenCL) from pip, service enabled
#   sudo deploy/install.sh --opencl apt    # PoCL from Debian (pocl-opencl-icd), e.g. 32-bit Pi OS
#   sudo deploy/install.sh --opencl vendor # the board's own OpenCL ICD (Mali, Jetson, ...)
#   deploy/install.sh --dry-run            # print every step, change nothing (no root needed)
#
# Steps: apt packages (python3-venv, binutils for PoCL's linker, the OpenCL ICD loader and
# driver) -> system user 'emdflow' in groups video, dialout -> venv in PREFIX with the
# package -> /etc/emdflow/emdflow.toml (kept if present) -> udev rule -> systemd unit.
set -euo pipefail

PREFIX=/opt/emdflow
CONF_DIR=/etc/emdflow
UNIT_DIR=/etc/systemd/system
UDEV_DIR=/etc/udev/rules.d
SERVICE_USER=emdflow
OPENCL=pip          # pip | apt | vendor
DEPTHAI=0
START=0
DRY_RUN=0
SRC="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"

usage() {
    sed -n '2,14p' "${BASH_SOURCE[0]}" | sed 's/^# \{0,1\}//'
    cat <<EOF

Options:
  --dry-run            print the commands instead of running them
  --prefix DIR         install the venv into DIR/venv (default $PREFIX)
  --user NAME          service user (default $SERVICE_USER)
  --opencl pip|apt|vendor
                       pip: pyopencl + PoCL wheels (x86_64, aarch64); apt: Debian's
                       pocl-opencl-icd; vendor: keep the board's ICD (default $OPENCL)
  --depthai            also install depthai (Luxonis OAK cameras)
  --start              start the service at the end (default: enable only)
  --source DIR         project checkout to install from (default $SRC)
EOF
}

while [ $# -gt 0 ]; do
    case "$1" in
        --dry-run) DRY_RUN=1 ;;
        --prefix) PREFIX="$2"; shift ;;
        --user) SERVICE_USER="$2"; shift ;;
        --opencl) OPENCL="$2"; shift ;;
        --depthai) DEPTHAI=1 ;;
        --start) START=1 ;;
        --source) SRC="$2"; shift ;;
        -h|--help) usage; exit 0 ;;
        *) echo "install.sh: unknown option '$1' (see --help)" >&2; exit 2 ;;
    esac
    shift
done
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

VENV="$PREFIX/venv"
APT_PKGS=(python3 python3-venv python3-pip binutils ocl-icd-libopencl1 clinfo)
EXTRAS=opencl
case "$OPENCL" in
    pip) EXTRAS=pocl ;;                       # pyopencl[pocl]: PoCL wheels, needs binutils' ld
    apt) APT_PKGS+=(pocl-opencl-icd) ;;        # Debian's PoCL, found through /etc/OpenCL/vendors
    vendor) ;;                                 # e.g. Mali (libmali), Jetson (nvidia-l4t), Rusticl
esac
[ "$DEPTHAI" = 1 ] && EXTRAS="$EXTRAS,depthai"

echo "== 1/6 system packages"
run apt-get update
run apt-get install -y --no-install-recommends "${APT_PKGS[@]}"

echo "== 2/6 service user '$SERVICE_USER' (groups video, dialout)"
if id "$SERVICE_USER" >/dev/null 2>&1; then
    run usermod -a -G video,dialout "$SERVICE_USER"
else
    run useradd --system --home-dir /var/lib/emdflow --no-create-home --shell /usr/sbin/nologin \
        --groups video,dialout "$SERVICE_USER"
fi

echo "== 3/6 Python venv in $VENV"
run mkdir -p "$PREFIX"
run python3 -m venv "$VENV"
run "$VENV/bin/pip" install --upgrade pip
run "$VENV/bin/pip" install "$SRC[$EXTRAS]"

echo "== 4/6 configuration $CONF_DIR/emdflow.toml"
run install -d -m 0755 "$CONF_DIR"
if [ -e "$CONF_DIR/emdflow.toml" ]; then
    echo "   keeping the existing $CONF_DIR/emdflow.toml (new example: $SRC/deploy/emdflow.toml)"
else
    run install -m 0644 "$SRC/deploy/emdflow.toml" "$CONF_DIR/emdflow.toml"
fi

echo "== 5/6 udev rule $UDEV_DIR/99-emdflow.rules (stable /dev/emdflow-camera, /dev/emdflow-fc)"
run install -m 0644 "$SRC/deploy/99-emdflow.rules" "$UDEV_DIR/99-emdflow.rules"
run udevadm control --reload-rules
run udevadm trigger

echo "== 6/6 systemd unit $UNIT_DIR/emdflowd.service"
UNIT_TMP="$(mktemp)"
trap 'rm -f "$UNIT_TMP"' EXIT
sed -e "s#^ExecStart=.*#ExecStart=$VENV/bin/emdflowd --config $CONF_DIR/emdflow.toml#" \
    -e "s#^User=.*#User=$SERVICE_USER#" -e "s#^Group=.*#Group=$SERVICE_USER#" \
    "$SRC/deploy/emdflowd.service" >"$UNIT_TMP"
run install -m 0644 "$UNIT_TMP" "$UNIT_DIR/emdflowd.service"
if command -v systemd-analyze >/dev/null 2>&1; then
    run systemd-analyze verify "$UNIT_DIR/emdflowd.service"
fi
run systemctl daemon-reload
run systemctl enable emdflowd.service
[ "$START" = 1 ] && run systemctl restart emdflowd.service

cat <<EOF

Done. Next:
  1. edit $CONF_DIR/emdflow.toml: [source] uri, [optics] focal_length_px, [link] port/baud/autopilot
  2. check the engine:   sudo -u $SERVICE_USER $VENV/bin/emdflowd --demo
  3. start the service:  sudo systemctl start emdflowd
  4. watch it:           journalctl -u emdflowd -f     (status line with latency p50/p99)
EOF
