"""The files that put a cell into service on its PC, shipped as package data beside this module: the
systemd unit and the service's user (``systemd/``), the VL53L8CX bridge board's udev rule (``udev/``).

A cell's PC has the wheel, not a checkout: ``cell deploy files DIR`` writes them out
(:func:`write_deploy_files`) to be copied into ``/etc`` (docs/deploy.md). The repository's ``deploy/``
links to these files.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

from drivers.errors import ConfigError

DEPLOY_FILES = ("systemd/cell.service", "systemd/cell.sysusers.conf", "udev/99-vl53l8cx.rules")
"""Each shipped file, by its path below this package (and below the folder it is written to)."""
UNIT = "systemd/cell.service"
UDEV_RULE = "udev/99-vl53l8cx.rules"
SERVICE_USER = "cell"
"""The user the shipped unit runs ``cell serve`` as (its ``User=``, made by ``cell.sysusers.conf``)."""


def deploy_file(name: str) -> Path:
    """The installed file ``name`` (one of :data:`DEPLOY_FILES`)."""
    if name not in DEPLOY_FILES:
        raise ConfigError(f"no deployment file {name!r}", allowed=", ".join(DEPLOY_FILES))
    return Path(str(files(__name__).joinpath(name)))


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
