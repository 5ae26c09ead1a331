"""One program of this machine drives an arm at a time (``drivers.arm.claim``): the claim file every user
shares, named by the arm's type and address."""

from __future__ import annotations

import os
import socket
import stat
from pathlib import Path

import pytest

from drivers.arm import claim
from drivers.arm.claim import ArmClaim, claim_path
from drivers.errors import DriverError


def test_a_host_name_and_the_address_it_resolves_to_are_one_arm() -> None:
    address = str(socket.getaddrinfo("localhost", None, type=socket.SOCK_STREAM)[0][4][0])
    assert claim_path("ur5e", "localhost") == claim_path("ur5e", address)
    assert claim_path("ur5e", address) != claim_path("franka", address)


def test_a_claim_file_is_every_users_whatever_the_umask_and_names_its_holder(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(claim, "LOCK_DIR", tmp_path)
    first, second = ArmClaim("ur5e", "10.9.8.7"), ArmClaim("ur5e", "10.9.8.7")
    umask = os.umask(0o077)
    try:
        first.take()
    finally:
        os.umask(umask)
    path = claim_path("ur5e", "10.9.8.7")
    assert path.parent == tmp_path and stat.S_IMODE(path.stat().st_mode) == 0o666
    with pytest.raises(DriverError, match=rf"driven by another program of this machine \(pid {os.getpid()}:"):
        second.check()
    first.release()
    second.take()  # the file is there: opened without O_CREAT, as a sticky folder needs for another user's
    second.release()
