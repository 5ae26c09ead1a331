"""The files that put a cell into service on its PC, shipped as package data beside this module: the
systemd unit and the service's user (``systemd/``), the VL53L8CX bridge board's udev rule (``udev/``).

A cell's PC has the wheel, not a checkout: ``cell deploy files DIR`` writes them out
(:func:`write_deploy_files`) to be copied into ``/etc`` (docs/deploy.md). The repository's ``deploy/``
links to these files.
"""

from __future__ import annotations

import shlex
from importlib.resources import files
from pathlib import Path

from drivers.errors import ConfigError

UNIT = "systemd/cell.service"
SYSUSERS = "systemd/cell.sysusers.conf"
UDEV_RULE = "udev/99-vl53l8cx.rules"
DEPLOY_FILES = (UNIT, SYSUSERS, UDEV_RULE)
"""Each shipped file, by its path below this package (and below the folder it is written to)."""
_INSTALL = {
    SYSUSERS: "sudo cp {path} /etc/sysusers.d/cell.conf && sudo systemd-sysusers",
    UDEV_RULE: "sudo cp {path} /etc/udev/rules.d/ && sudo udevadm control --reload && sudo udevadm trigger",
    UNIT: "sudo cp {path} /etc/systemd/system/ && sudo systemctl daemon-reload",
}
"""How each shipped file is installed, in the order docs/deploy.md installs them (sections 3, 4 and 6)."""
DATA_DIR = "/var/lib/cell"
"""The service's data folder under the shipped unit (its ``--data-dir`` and ``StateDirectory=``)."""
SERVICE_USER = "cell"
"""The user the shipped unit runs ``cell serve`` as (its ``User=``, made by ``cell.sysusers.conf``)."""


def deploy_file(name: str) -> Path:
    """The installed file ``name`` (one of :data:`DEPLOY_FILES`)."""
    if name not in DEPLOY_FILES:
        raise ConfigError(f"no deployment file {name!r}", allowed=", ".join(DEPLOY_FILES))
    return Path(str(files(__name__).joinpath(name)))


def install_command(name: str, folder: Path) -> str:
    """The command that installs the file ``name`` (one of :data:`DEPLOY_FILES`) written below ``folder``."""
    return _INSTALL[name].format(path=shlex.quote(str(folder / name)))


def install_commands(folder: Path) -> list[str]:
    """The commands that install the files written to ``folder``, in order."""
    return [install_command(name, folder) for name in _INSTALL]


def write_deploy_files(folder: Path) -> list[Path]:
    """Write every file of :data:`DEPLOY_FILES` below ``folder`` (made if missing), keeping their
    sub-folders; returns the files written. Never overwrites one: ``ConfigError`` naming those that exist
    (then nothing is written), or the folder that cannot be written."""
    targets = {name: folder / name for name in DEPLOY_FILES}
    taken = [str(path) for path in targets.values() if path.exists()]
    if taken:
        raise ConfigError(f"exists already: {', '.join(taken)}; cell deploy files never overwrites a file",
                          file=str(folder))
    try:
        for name, target in targets.items():
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(deploy_file(name).read_bytes())
    except OSError as exc:
        raise ConfigError(f"cannot write the deployment files: {exc.strerror}", file=str(folder)) from None
    return list(targets.values())
