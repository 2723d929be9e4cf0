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
from daemon_util import REPO, opencl_available, run_cli  # noqa: E402

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
                 "DeviceAllow=char-drm rw", "RestartPreventExitStatus=2", "IPAddressDeny=any",
                 "DeviceAllow=char-ttyTHS rw"):  # Jetson's header UARTs (/dev/ttyTHS*)
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
    # (--man=no, as install.sh runs it: the Documentation= man page may not be installed)
    result = subprocess.run(["systemd-analyze", "verify", "--man=no", str(path)], capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 0, result.stderr
    # verify only warns about unknown keys or bad values: any line about our file is a failure
    complaints = [l for l in result.stderr.splitlines() if "emdflowd.service" in l]
    assert not complaints, complaints


def test_install_script_dry_run_changes_nothing(tmp_path):
    before = os.path.exists("/etc/emdflow/emdflow.toml"), os.path.exists("/etc/systemd/system/emdflowd.service")
    result = _dry_run("--prefix", tmp_path / "opt", "--opencl", "apt", "--depthai")
    assert result.returncode == 0, result.stderr
    out = result.stdout
    for expected in ("apt-get install -y --no-install-recommends", "pocl-opencl-icd", "binutils",
                     "python3-venv", "useradd --system", "video,dialout", f"python3 -m venv {tmp_path}/opt/venv",
                     f"{REPO}[opencl,depthai]", "/etc/emdflow/emdflow.toml", "99-emdflow.rules",
                     "/etc/systemd/system/emdflowd.service", "systemctl enable emdflowd.service"):
        assert expected in out, expected
    if shutil.which("systemd-analyze"):  # (checked without the man pages a minimal image lacks)
        assert "systemd-analyze verify --man=no /etc/systemd/system/emdflowd.service" in out
    assert not (tmp_path / "opt").exists()
    after = os.path.exists("/etc/emdflow/emdflow.toml"), os.path.exists("/etc/systemd/system/emdflowd.service")
    assert before == after


def test_install_script_rejects_bad_options():
    result = _dry_run("--opencl", "cuda")
    assert result.returncode == 2 and "--opencl must be pip, apt or vendor" in result.stderr
    default = _dry_run()
    assert default.returncode == 0 and f"{REPO}[pocl]" in default.stdout
    # pip's PoCL is checked on this processor right after the install (Debian's is added
    # where it cannot build the kernels); with Debian's or a vendor's PoCL there is no check
    pip_install = default.stdout.index(f"{REPO}[pocl]")
    assert default.stdout.index("bin/emdflow devices") > pip_install
    assert "bin/emdflow devices" not in _dry_run("--opencl", "apt").stdout


def test_udev_rules_are_well_formed():
    rules = [l for l in (DEPLOY / "99-emdflow.rules").read_text().splitlines() if l and not l.startswith("#")]
    assert any('SYMLINK+="emdflow-camera"' in l and 'SUBSYSTEM=="video4linux"' in l for l in rules)
    assert any('SYMLINK+="emdflow-fc"' in l and 'SUBSYSTEM=="tty"' in l for l in rules)
    for line in rules:
        for item in line.split(", "):
            assert re.fullmatch(r'[A-Z]+(\{[a-zA-Z_]+\})?(==|\+=|=)"[^"]*"', item), item


def _dry_run(*args, env=None):
    """``deploy/install.sh --dry-run`` with ``args``: prints what it would do, changes nothing."""
    return subprocess.run(["bash", str(DEPLOY / "install.sh"), "--dry-run", *map(str, args)],
                          capture_output=True, text=True, timeout=60, env=env)


def _unit_environment():
    return dict(line.split("=", 2)[1:] for line in _unit().splitlines() if line.startswith("Environment="))


def test_install_creates_the_service_directories_before_the_engine_check(tmp_path):
    """The engine check runs as the service user before the service ever started: its home
    and PoCL's cache must exist (systemd makes them only at the first start)."""
    env = _unit_environment()
    assert {"HOME", "XDG_CACHE_HOME", "POCL_CACHE_DIR"} <= env.keys()
    unit = _unit()
    assert "StateDirectory=emdflow" in unit and env["HOME"] == "/var/lib/emdflow"
    assert "CacheDirectory=emdflow" in unit and env["POCL_CACHE_DIR"].startswith("/var/cache/emdflow/")
    result = _dry_run("--prefix", tmp_path / "opt", "--user", "flowuser")
    assert result.returncode == 0, result.stderr
    out = result.stdout
    made = re.findall(r"^\+ install -d -o flowuser -g flowuser -m \d+ (.+)$", out, re.M)
    made = {path for line in made for path in line.split()}
    assert {env["HOME"], env["XDG_CACHE_HOME"], env["POCL_CACHE_DIR"]} <= made, out
    assert out.index("useradd --system") < out.index("install -d -o flowuser") < out.index("-m venv")
    # the check command printed at the end runs in the unit's environment
    check = next(line for line in out.splitlines() if "emdflowd --demo" in line)
    assert check.split()[:3] == ["sudo", "-u", "flowuser"] and check.split()[3] == "env", check
    for key in ("HOME", "XDG_CACHE_HOME", "POCL_CACHE_DIR"):
        assert f" {key}={env[key]} " in check, (key, check)


def test_readme_engine_check_uses_the_units_environment():
    readme = (REPO / "README.md").read_text()
    section = readme[readme.index("### Installing the service"):readme.index("### Tests")]
    command = re.search(r"sudo -u emdflow env (.*?)/opt/emdflow/venv/bin/emdflowd --demo", section, re.S)
    assert command, "no engine check with the unit's environment in the README"
    assigned = dict(item.split("=", 1) for item in command.group(1).replace("\\", " ").split())
    env = _unit_environment()
    assert assigned == {key: env[key] for key in ("HOME", "XDG_CACHE_HOME", "POCL_CACHE_DIR")}


@pytest.mark.skipif(not opencl_available(), reason="no OpenCL platform")
def test_engine_check_works_without_a_home_once_the_cache_exists(tmp_path):
    """A fresh service user has no writable home; with the cache directory install.sh
    creates, passed as the unit's environment passes it, the engine check runs on PoCL."""
    cache = tmp_path / "cache"
    (cache / "pocl").mkdir(parents=True)
    env = {"HOME": "/proc/emdflow-home", "XDG_CACHE_HOME": str(cache), "POCL_CACHE_DIR": str(cache / "pocl")}
    result = run_cli(["--demo", "--frames", 20], timeout=300, env=env)
    assert result.returncode == 0, result.stderr[-2000:] + result.stdout[-2000:]
    assert any((cache / "pocl").iterdir())                      # kernels cached where the unit says


def test_install_stops_on_an_old_python_before_changing_anything(tmp_path):
    old = tmp_path / "python3.9"
    old.write_text("#!/bin/sh\necho 3.9.2\nexit 1\n")         # stands in for Debian 11's python3
    old.chmod(0o755)
    result = _dry_run("--python", old)
    assert result.returncode == 1
    assert f"'{old}' is Python 3.9.2; emdflow needs Python >= 3.11 (tomllib)" in result.stderr
    assert "--python python3.11" in result.stderr
    for step in ("apt-get", "useradd", "install -d", "venv"):
        assert step not in result.stdout, step
    missing = _dry_run("--python", tmp_path / "nothere")
    assert missing.returncode == 1 and "cannot run" in missing.stderr and "useradd" not in missing.stdout
    good = _dry_run("--python", sys.executable, "--prefix", tmp_path / "opt")
    assert good.returncode == 0, good.stderr
    assert f"{sys.executable} -m venv {tmp_path}/opt/venv" in good.stdout
    versioned = _dry_run("--python", "python3.11", "--prefix", tmp_path / "opt")
    assert "python3.11 python3.11-venv" in versioned.stdout     # Ubuntu 22.04's extra interpreter


def test_install_adds_the_service_user_to_render_where_that_group_exists(tmp_path):
    """A GPU OpenCL driver opens /dev/dri/renderD*, owned by group 'render': the service
    user joins it where the group exists (a getent stand-in says so here), and not where
    it does not (this machine)."""
    shim = tmp_path / "bin"
    shim.mkdir()
    (shim / "getent").write_text('#!/bin/sh\n[ "$1 $2" = "group render" ] && echo "render:x:993:" && exit 0\nexit 2\n')
    (shim / "getent").chmod(0o755)
    env = dict(os.environ, PATH=f"{shim}:{os.environ['PATH']}")
    with_render = _dry_run(env=env)
    assert with_render.returncode == 0, with_render.stderr
    assert "--groups video,dialout,render emdflow" in with_render.stdout
    (shim / "getent").write_text("#!/bin/sh\nexit 2\n")
    without = _dry_run(env=env)
    assert "--groups video,dialout emdflow" in without.stdout


def test_install_updates_an_unedited_udev_rule_and_keeps_an_edited_one(tmp_path):
    """The rule is meant to be edited: one equal to the example the last install shipped
    (kept beside it) is updated, one that differs from it stays, like the configuration."""
    shipped = (DEPLOY / "99-emdflow.rules").read_text()
    udev = tmp_path / "rules.d"
    udev.mkdir()
    rule, example = udev / "99-emdflow.rules", udev / "99-emdflow.rules.example"

    def install():
        out = _dry_run("--udev-dir", udev).stdout
        return out[out.index("== 6/7"):out.index("== 7/7")]

    assert f"install -m 0644 {DEPLOY}/99-emdflow.rules {rule}\n" in install()       # none yet
    rule.write_text("# an older example\n")
    example.write_text("# an older example\n")
    assert f"{rule}\n" in install() and "keeping" not in install()                   # unedited: updated
    rule.write_text("# an older example\nSUBSYSTEM==\"tty\", SYMLINK+=\"emdflow-fc\"\n")
    step = install()
    assert f"keeping {rule}" in step and f"0644 {DEPLOY}/99-emdflow.rules {rule}\n" not in step
    assert f"{example}" in step                                                      # the new example beside it
    rule.write_text(shipped)
    assert "keeping" not in install()                                                # already current


@pytest.mark.parametrize("arch", ["aarch64", "x86_64"])
def test_install_takes_debians_pocl_where_pip_has_none(tmp_path, arch):
    """PyPI's PoCL wheel is x86_64 only: on a Pi or a Jetson the default install stopped at
    pip, after the user and its folders were made. The default is now Debian's PoCL there,
    and an explicit --opencl pip is refused before any step. (`uname -m` answers from a
    stand-in on PATH: this machine is x86_64.)"""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "uname").write_text(f"#!/bin/sh\necho {arch}\n")
    (bin_dir / "uname").chmod(0o755)
    env = dict(os.environ, PATH=f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    default = _dry_run("--prefix", tmp_path / "opt", env=env)
    assert default.returncode == 0, default.stderr
    packages = next(line for line in default.stdout.splitlines() if "apt-get install" in line)
    pip = next(line for line in default.stdout.splitlines() if "pip install" in line and "[" in line)
    if arch == "aarch64":
        assert "pocl-opencl-icd" in packages and pip.endswith("[opencl]"), (packages, pip)
    else:
        assert "pocl-opencl-icd" not in packages and pip.endswith("[pocl]"), (packages, pip)
    explicit = _dry_run("--prefix", tmp_path / "opt", "--opencl", "pip", env=env)
    if arch == "aarch64":
        assert explicit.returncode == 2 and "+ " not in explicit.stdout
        assert "--opencl pip: PyPI's PoCL wheel is built for x86_64 only, this is aarch64" in explicit.stderr
    else:
        assert explicit.returncode == 0 and "[pocl]" in explicit.stdout


def test_install_refuses_an_option_without_its_value_and_relative_folders(tmp_path):
    """`--prefix --dry-run` took "--dry-run" as the prefix and ran a real install; a
    missing last value was bash's "unbound variable"; a relative prefix planned a unit
    systemd rejects (ExecStart= must be absolute). Each is a usage error, nothing done."""
    script = str(DEPLOY / "install.sh")
    # (always a dry run first: a script that took "--dry-run" as the prefix again must not
    # install anything on the machine running the tests)
    for args in (["--dry-run", "--prefix", "--dry-run"], ["--dry-run", "--prefix"], ["--dry-run", "--user", ""],
                 ["--dry-run", "--python"]):
        result = subprocess.run(["bash", script, *args], capture_output=True, text=True, timeout=60)
        assert result.returncode == 2, (args, result.stdout, result.stderr)
        assert f"install.sh: {args[1]} needs a value" in result.stderr
        assert "+ " not in result.stdout
    for option in ("--prefix", "--udev-dir"):
        result = _dry_run(option, "opt/emdflow")
        assert result.returncode == 2 and "opt/emdflow: give an absolute path" in result.stderr
    assert _dry_run("--prefix", tmp_path / "opt").returncode == 0


def test_install_refuses_a_prefix_the_units_execstart_cannot_hold(tmp_path):
    """The prefix reaches the unit's ExecStart= through sed's replacement (where & is the
    matched line, # ends the expression and \\ escapes) and then systemd (whitespace splits
    the command, % and $ are expanded): "/srv/e&f" wrote ExecStart=/srv/eExecStart=...f/...
    Each is refused before anything is done (always as a dry run: _dry_run passes --dry-run first)."""
    for prefix in ("/srv/e&f", "/srv/a#b", "/srv/a\\b", "/srv/my flow", "/srv/a\tb", "/srv/a\nb",
                   "/srv/100%", "/srv/$HOME", '/srv/a"b', "/srv/a'b"):
        result = _dry_run("--prefix", prefix)
        assert result.returncode == 2, (prefix, result.stdout, result.stderr)
        assert f"install.sh: --prefix '{prefix}': the unit's ExecStart= cannot hold" in result.stderr
        assert "+ " not in result.stdout, prefix
    ok = tmp_path / "emdflow-1.2_x+y@host,z=~"
    result = _dry_run("--prefix", ok)
    assert result.returncode == 0, result.stderr
    assert f"+ mkdir -p {ok}" in result.stdout


def test_install_refuses_a_user_name_the_unit_cannot_hold():
    """--user reaches the unit's User= and Group= through the same sed replacement: only a
    user name as useradd takes one passes (always as a dry run)."""
    for user in ("a b", "x&y", "a#b", "a\\b", "ro$t", "a/b"):
        result = _dry_run("--user", user)
        assert result.returncode == 2, (user, result.stdout, result.stderr)
        assert f"install.sh: --user '{user}': expected a user name" in result.stderr
        assert "+ " not in result.stdout, user
    for user in ("emdflow", "pi", "flow_1.x-y"):
        result = _dry_run("--user", user)
        assert result.returncode == 0, (user, result.stderr)
        assert f"'{user}'" in result.stdout
