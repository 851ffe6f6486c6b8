"""scripts/setup.sh installs system packages through scripts/apt_install.sh: it waits for another apt's dpkg lock,
and when apt fails anyway it shows apt's own reason under its warning (a fake apt-get stands in for apt)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LOCKED = "E: Could not get lock /var/lib/dpkg/lock-frontend. It is held by process 4242 (unattended-upgr)"


def _apt_install(tmp_path: Path, install_fails: bool) -> tuple[subprocess.CompletedProcess, list[str]]:
    fake = tmp_path / "bin" / "apt-get"
    fake.parent.mkdir(exist_ok=True)
    calls = tmp_path / "calls"
    fake.write_text(f"""#!/usr/bin/env bash
echo "$*" >> {calls}
echo "Reading package lists..."
if [ {int(install_fails)} = 1 ] && [[ " $* " == *" install "* ]]; then echo "{LOCKED}" >&2; exit 100; fi
""")
    fake.chmod(0o755)
    env = {**os.environ, "PATH": f"{fake.parent}:{os.environ['PATH']}"}
    script = f"source {ROOT / 'scripts' / 'apt_install.sh'}; apt_install 'could not install xvfb; it skips' xvfb xauth"
    run = subprocess.run(["bash", "-c", script], capture_output=True, text=True, env=env)
    return run, calls.read_text().splitlines()


def test_apt_failure_shows_apt_reason_and_waits_for_the_lock(tmp_path):
    run, calls = _apt_install(tmp_path, install_fails=True)
    assert run.returncode == 100 and run.stdout == ""
    assert run.stderr == f"warning: could not install xvfb; it skips\n  apt-get: {LOCKED}\n"
    assert calls == ["-o DPkg::Lock::Timeout=120 update -qq",
                     "-o DPkg::Lock::Timeout=120 install -y -qq --no-install-recommends xvfb xauth"]


def test_apt_success_is_quiet_and_setup_installs_only_through_it(tmp_path):
    run, calls = _apt_install(tmp_path, install_fails=False)
    assert run.returncode == 0 and run.stdout == run.stderr == "" and len(calls) == 2
    setup = (ROOT / "scripts" / "setup.sh").read_text()
    assert "source scripts/apt_install.sh" in setup and setup.count("apt_install \"") == 3
    assert "apt-get update" not in setup and "apt-get install -y -qq" not in setup  # every install: the helper
