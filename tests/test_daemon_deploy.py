"""Service integration: sd_notify over a real socket, the systemd unit, the install script."""

from __future__ import annotations

import os
import re
import shutil
import socket
import subprocess
import sys

import pytest

from firmware_py.sdnotify import Notifier
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # shared helpers
from daemon_util import REPO  # noqa: E402

DEPLOY = REPO / "deploy"


def _bound_socket(path):
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.settimeout(2.0)
    return sock


def test_notifier_speaks_the_sd_notify_protocol(tmp_path, monkeypatch):
    path = str(tmp_path / "notify.sock")
    server = _bound_socket(path)
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    monkeypatch.setenv("WATCHDOG_USEC", "4000000")
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    notifier = Notifier()
    assert notifier.enabled and notifier.watchdog_interval_s == 2.0
    assert notifier.ready("running synthetic:")
    assert server.recv(1024) == b"READY=1\nSTATUS=running synthetic:"
    notifier.watchdog()
    assert server.recv(1024) == b"WATCHDOG=1"
    notifier.status("99.0 fps")
    assert server.recv(1024) == b"STATUS=99.0 fps"
    notifier.stopping()
    assert server.recv(1024) == b"STOPPING=1"
    server.close()
    assert not notifier.watchdog()  # the socket went away: no exception, just False
    notifier.close()


def test_notifier_abstract_socket_and_absent(monkeypatch):
    name = f"emdflow-test-{os.getpid()}"
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind("\0" + name)
    server.settimeout(2.0)
    assert Notifier("@" + name).ready()
    assert server.recv(64) == b"READY=1"
    server.close()
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    monkeypatch.setenv("WATCHDOG_USEC", "4000000")
    monkeypatch.setenv("WATCHDOG_PID", "1")  # meant for another process
    quiet = Notifier()
    assert not quiet.enabled and not quiet.ready() and quiet.watchdog_interval_s is None


def _unit():
    return (DEPLOY / "emdflowd.service").read_text()


def test_unit_has_the_required_directives():
    unit = _unit()
    for line in ("Type=notify", "User=emdflow", "SupplementaryGroups=video dialout", "Restart=on-failure",
                 "NoNewPrivileges=yes", "ProtectSystem=strict", "ProtectHome=yes", "PrivateTmp=yes",
                 "CacheDirectory=emdflow", "Environment=POCL_CACHE_DIR=/var/cache/emdflow/pocl",
                 "DevicePolicy=closed", "DeviceAllow=char-video4linux rw", "DeviceAllow=char-ttyAMA rw",
                 "DeviceAllow=char-drm rw", "RestartPreventExitStatus=2", "IPAddressDeny=any"):
        assert re.search(rf"^{re.escape(line)}$", unit, re.M), line
    assert re.search(r"^WatchdogSec=\d+", unit, re.M)
    assert re.search(r"^ExecStart=\S*emdflowd --config /etc/emdflow/emdflow.toml$", unit, re.M)
    assert "MemoryDenyWriteExecute" not in unit.replace("No MemoryDenyWriteExecute", "")  # PoCL JIT


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_unit_passes_systemd_analyze_verify(tmp_path):
    # verify insists that ExecStart exists: point it at this interpreter, keep everything else
    unit = re.sub(r"^ExecStart=\S+", f"ExecStart={sys.executable} -m firmware_py.cli", _unit(), flags=re.M)
    path = tmp_path / "emdflowd.service"
    path.write_text(unit)
    result = subprocess.run(["systemd-analyze", "verify", str(path)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    # verify only warns about unknown keys or bad values: any line about our file is a failure
    complaints = [l for l in result.stderr.splitlines() if "emdflowd.service" in l]
    assert not complaints, complaints


def test_install_script_dry_run_changes_nothing(tmp_path):
    before = os.path.exists("/etc/emdflow/emdflow.toml"), os.path.exists("/etc/systemd/system/emdflowd.service")
    result = subprocess.run(["bash", str(DEPLOY / "install.sh"), "--dry-run", "--prefix", str(tmp_path / "opt"),
                             "--opencl", "apt", "--depthai"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    out = result.stdout
    for expected in ("apt-get install -y --no-install-recommends", "pocl-opencl-icd", "binutils",
                     "python3-venv", "useradd --system", "video,dialout", f"python3 -m venv {tmp_path}/opt/venv",
                     f"{REPO}[opencl,depthai]", "/etc/emdflow/emdflow.toml", "99-emdflow.rules",
                     "/etc/systemd/system/emdflowd.service", "systemctl enable emdflowd.service"):
        assert expected in out, expected
    assert not (tmp_path / "opt").exists()
    after = os.path.exists("/etc/emdflow/emdflow.toml"), os.path.exists("/etc/systemd/system/emdflowd.service")
    assert before == after


def test_install_script_rejects_bad_options():
    result = subprocess.run(["bash", str(DEPLOY / "install.sh"), "--dry-run", "--opencl", "cuda"],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "--opencl must be pip, apt or vendor" in result.stderr
    default = subprocess.run(["bash", str(DEPLOY / "install.sh"), "--dry-run"], capture_output=True, text=True,
                             timeout=60)
    assert default.returncode == 0 and f"{REPO}[pocl]" in default.stdout


def test_udev_rules_are_well_formed():
    rules = [l for l in (DEPLOY / "99-emdflow.rules").read_text().splitlines() if l and not l.startswith("#")]
    assert any('SYMLINK+="emdflow-camera"' in l and 'SUBSYSTEM=="video4linux"' in l for l in rules)
    assert any('SYMLINK+="emdflow-fc"' in l and 'SUBSYSTEM=="tty"' in l for l in rules)
    for line in rules:
        for item in line.split(", "):
            assert re.fullmatch(r'[A-Z]+(\{[a-zA-Z_]+\})?(==|\+=|=)"[^"]*"', item), item
