"""Checks of this computer: Python and packages, the compiled kernels, system libraries, the clock, the
CPU frequency governor, real-time scheduling limits, free disk, and the service's ports."""

from __future__ import annotations

import ctypes
import errno
import http.client
import importlib
import json
import os
import platform
import pwd
import resource
import shutil
import sys
from importlib import metadata
from pathlib import Path

from cell.deploy import SERVICE_USER
from cell.doctor.findings import Finding
from cell.service.instance import Instance, instance_of
from cell.service.store.engine import hide_password, schema_head, sqlite_access_problem, sqlite_database
from cell.service.store.repository import inspect_store
from cell.service.store.service_store import service_store_url
from drivers.errors import DriverError, StoreDamaged, StoreError
from drivers.file_access import access_problem, make_folder, user_name
from drivers.hosts import is_loopback, listen_problem
from drivers.sim.board import import_cv2

PYTHON = (3, 11)
CORE_PACKAGES = ("numpy", "open3d-cpu", "ruckig", "python-fcl", "fastapi", "uvicorn", "sqlalchemy", "asyncua")
KERNELS = ("cell.perception._kernels", "cell.planning.vs._objective", "cell.planning.lrnbv._raygains")
# Open3D's shared libraries and the Debian package that has each
SYSTEM_LIBRARIES = {"libusb-1.0.so.0": "libusb-1.0-0", "libgomp.so.1": "libgomp1", "libGL.so.1": "libgl1"}
DISK_FAIL_GB = 1.0
"""Below this a scan's folder (frames, clouds: tens to hundreds of MB) may not fit [GB]."""
DISK_WARN_GB = 10.0
"""Below this a day of scanning may fill the disk; set service.retention [GB]."""
RT_PRIORITY = 99
"""libfranka raises its control thread to SCHED_FIFO's highest priority (99)."""
RT_LIMITS_FILE = "/etc/security/limits.d/cell.conf"
SERVICE_ANSWER_TIMEOUT_S = 2.0
"""How long [s] the check of a port in use waits for a service there to answer ``/healthz``."""
HEALTHZ_MAX_BYTES = 4096
"""The most of an answer to ``/healthz`` [bytes] that check reads."""
IN_USE = os.strerror(errno.EADDRINUSE)
"""Why a port another process listens on cannot be listened on (``listen_problem``'s words)."""
NOT_A_FOLDER_FIX = "give --data-dir a folder (or a name not taken)"
"""The fix of a ``--data-dir`` that names a file (the disk and the job store checks)."""
TIME_ERROR = 5
"""adjtimex(2)'s answer when the kernel's clock is not synchronised (TIME_ERROR)."""
GOVERNORS = Path("/sys/devices/system/cpu")
STORE_CONNECT_TIMEOUT_S = 2
"""How long the store's server may take to accept a connection [s]: libpq counts whole seconds, and
takes any less than 2 as 2."""


def python_version() -> Finding:
    found = platform.python_version()
    if sys.version_info[:2] != PYTHON:
        wanted = f"{PYTHON[0]}.{PYTHON[1]}"
        return Finding.fail("python", found, f"install Python {wanted} and the cell in a venv of it")
    return Finding.ok("python", f"{found} ({sys.executable})")


def packages(extras: dict[str, str]) -> list[Finding]:
    """The cell's and its main dependencies' versions, and each package the cell file needs
    (``extras``: distribution name -> the extra that installs it)."""
    try:
        versions = [f"cell {metadata.version('cell')}"]
    except metadata.PackageNotFoundError:
        versions = ["cell (not installed as a package)"]
    missing = []
    for name in CORE_PACKAGES:
        try:
            versions.append(f"{name} {metadata.version(name)}")
        except metadata.PackageNotFoundError:
            missing.append(name)
    found = [Finding.ok("packages", ", ".join(versions)) if not missing else Finding.fail(
        "packages", f"missing: {', '.join(missing)}", "reinstall: pip install --force-reinstall cell")]
    for name, extra in extras.items():
        try:
            found.append(Finding.ok(f"package {name}", metadata.version(name)))
        except metadata.PackageNotFoundError:
            found.append(Finding.fail(f"package {name}", "not installed, and the cell file needs it",
                                      f"pip install 'cell[{extra}]'"))
    return found


def board_support() -> Finding:
    """Whether OpenCV loads with what the ChArUco board needs (aruco, ``calibrateHandEye``): a cell file
    with a ``calibration.board`` is calibrated with it. A warning only: the cell scans without it."""
    try:
        cv2 = import_cv2()
    except DriverError:
        return Finding.warn("package opencv", "not installed, or without aruco and calibrateHandEye: cell "
                            "calibrate mount --target charuco and cell calibrate board need it for the cell "
                            "file's calibration.board", "pip install 'cell[calibration]'")
    return Finding.ok("package opencv", str(cv2.__version__))


def kernels() -> Finding:
    broken = []
    for module in KERNELS:
        try:
            importlib.import_module(module)
        except ImportError as exc:
            broken.append(f"{module} ({exc})")
    if broken:
        return Finding.fail("compiled kernels", f"cannot load {'; '.join(broken)}",
                            "reinstall the cell's wheel for this Python (a build needs gcc and python3-dev)")
    return Finding.ok("compiled kernels", f"{len(KERNELS)} load")


def system_libraries() -> Finding:
    missing = []
    for library, package in SYSTEM_LIBRARIES.items():
        try:
            ctypes.CDLL(library)
        except OSError:
            missing.append(package)
    if missing:
        return Finding.fail("system libraries", f"Open3D needs {', '.join(missing)}",
                            f"sudo apt install {' '.join(missing)}")
    return Finding.ok("system libraries", ", ".join(SYSTEM_LIBRARIES))


class _Timex(ctypes.Structure):
    # adjtimex(2) reads and writes a struct timex; with modes 0 it only reads. Its size is below 256
    # bytes on every Linux ABI: a zeroed buffer of that size is what the call needs.
    _fields_ = [("modes", ctypes.c_uint), ("rest", ctypes.c_byte * 252)]


def clock_sync() -> Finding:
    """The kernel's own view (adjtimex), set by whichever NTP client runs (timesyncd, chrony, ntpd)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        state = libc.adjtimex(ctypes.byref(_Timex()))
    except (OSError, AttributeError):
        return Finding.warn("clock", "cannot ask the kernel whether the clock is synchronised",
                            "check `timedatectl` says 'System clock synchronized: yes'")
    if state == TIME_ERROR or state < 0:
        return Finding.warn("clock", "not synchronised: job times, logs and the line's timestamps drift",
                            "sudo timedatectl set-ntp true (or point chrony at the plant's time server)")
    return Finding.ok("clock", "synchronised")


def cpu_governor(root: Path = GOVERNORS) -> Finding:
    files = sorted(root.glob("cpu[0-9]*/cpufreq/scaling_governor"))
    if not files:
        return Finding.ok("cpu governor", "no frequency scaling exposed (fixed clock or a virtual machine)")
    governors = {f.read_text().strip() for f in files}
    if governors != {"performance"}:
        return Finding.warn("cpu governor", f"{', '.join(sorted(governors))}: the control loop's timing "
                            "jitters as the clock ramps", "sudo cpupower frequency-set -g performance "
                            "(persist it in /etc/default/cpupower)")
    return Finding.ok("cpu governor", "performance")


def service_user_note() -> str:
    """A note for a fix that this user applies, when the shipped unit's user (:data:`SERVICE_USER`) exists
    on this machine and is another: the service runs as that one, which doctor should be run as
    (docs/deploy.md, section 5); else nothing."""
    try:
        pwd.getpwnam(SERVICE_USER)
    except KeyError:
        return ""
    if user_name() == SERVICE_USER:
        return ""
    return (f" (the service runs as {SERVICE_USER}: run doctor as it, sudo -u {SERVICE_USER} cell doctor "
            "...)")


def realtime_limits(required: bool) -> Finding:
    """Whether this user may run a thread at SCHED_FIFO priority 99 (``required``: the Franka with
    ``realtime: enforce``), and whether the kernel is PREEMPT_RT. Only a Franka's 1 kHz loop (libfranka)
    needs either: the caller checks them for a Franka cell only."""
    soft, _hard = resource.getrlimit(resource.RLIMIT_RTPRIO)
    allowed = os.geteuid() == 0 or soft == resource.RLIM_INFINITY or soft >= RT_PRIORITY
    flag = Path("/sys/kernel/realtime")
    rt_kernel = flag.is_file() and flag.read_text().strip() == "1"
    if not allowed:
        who = user_name()
        fix = (f"printf '%s\\n' '{who} - rtprio {RT_PRIORITY}' '{who} - memlock unlimited' | sudo tee "
               f"{RT_LIMITS_FILE}, then log in again (cell serve under the shipped unit has both from its "
               "LimitRTPRIO and LimitMEMLOCK)")
        text = f"real-time priority up to {soft}, {RT_PRIORITY} needed"
        return Finding.fail("real-time", text, fix) if required else Finding.warn("real-time", text, fix)
    if not rt_kernel:
        text = "allowed, but the kernel is not PREEMPT_RT"
        fix = "install a real-time kernel (Debian: linux-image-rt-amd64) and boot it"
        return Finding.warn("real-time", text, fix) if required else Finding.ok("real-time", text)
    return Finding.ok("real-time", f"priority {RT_PRIORITY} allowed, PREEMPT_RT kernel")


def disk(data_dir: Path) -> Finding:
    """Free space under the data folder (or the folder it will be made in), which must be a folder this
    user may write."""
    where = data_dir
    while not where.exists() and where != where.parent:
        where = where.parent
    if not where.is_dir():
        return Finding.fail("disk", f"{where} is not a folder: cell serve keeps its jobs and store in "
                            f"--data-dir {data_dir}", NOT_A_FOLDER_FIX)
    free_gb = shutil.disk_usage(where).free / 1e9
    problem = access_problem(where, folder=True, recursive=True, instead="choose another --data-dir")
    if problem is not None:
        # a folder above a data folder not made yet is the system's: the data folder is made, not it given
        fix = problem.fix if where == data_dir or problem.read_only else make_folder(data_dir)
        return Finding.fail("disk", problem.found, fix + service_user_note())
    text = f"{free_gb:.1f} GB free under {where}"
    fix = "free space, or set service.retention (days, max_gb) so that old jobs are pruned"
    if free_gb < DISK_FAIL_GB:
        return Finding.fail("disk", text, fix)
    if free_gb < DISK_WARN_GB:
        return Finding.warn("disk", text, fix)
    return Finding.ok("disk", text)


def serves_cell(host: str, port: int, data_dir: Path) -> Instance | None:
    """What the running service of ``data_dir`` wrote there (``cell.service.instance``) when it answers on
    ``host``:``port`` (its ``/healthz`` says the id its start wrote), else None. The service port is then
    its, not another program's; an OPC UA port only when it wrote that it listens there."""
    expected = instance_of(data_dir)
    if expected is None:
        return None
    connection = http.client.HTTPConnection(host, port, timeout=SERVICE_ANSWER_TIMEOUT_S)
    try:
        connection.request("GET", "/healthz")
        answer = connection.getresponse()
        # a cell's answer is a few dozen bytes: another program's longer one is read no further
        body = json.loads(answer.read(HEALTHZ_MAX_BYTES)) if answer.status == 200 else None
    except (OSError, http.client.HTTPException, ValueError):  # nothing there, or not a cell's service
        return None
    finally:
        connection.close()
    return expected if isinstance(body, dict) and body.get("instance") == expected.id else None


def listen_fix(problem: str, host: str, in_use: str, host_setting: str, port_setting: str) -> str:
    """What to do when a server cannot listen on ``host`` for ``problem`` (``listen_problem``'s words):
    ``in_use`` for a port another program holds; else the port (one the system keeps) or the host (not
    this machine's: a PLC network's address on another PC, a name that does not resolve) to correct in
    the setting that names it. Both had been told "another program has it", sending the engineer after a
    program that is not there."""
    if problem == IN_USE:
        return in_use
    if problem == os.strerror(errno.EACCES):
        return f"a port below 1024 is the system's: choose one from 1024 up ({port_setting})"
    return (f"{host} is no name or address of this machine (ip -brief address lists them; 0.0.0.0 is every "
            f"one): correct it ({host_setting})")


def port_free(host: str, port: int, name: str = "service port", served: bool = False) -> Finding:
    """Whether the service can listen on ``host``:``port``; a port in use is fine when ``served``: this
    cell's running service holds it (:func:`serves_cell`)."""
    problem = listen_problem(host, port)
    if problem == IN_USE and served:
        return Finding.ok(name, f"{host}:{port} is in use by this cell's running service")
    if problem is not None:
        in_use = f"another program has it (sudo ss -ltnp 'sport = :{port}'): stop it, or choose another port"
        return Finding.fail(name, f"cannot listen on {host}:{port}: {problem}",
                            listen_fix(problem, host, in_use, "cell serve --host", "cell serve --port"))
    return Finding.ok(name, f"{host}:{port} is free")


def store(data_dir: Path, db_url: str | None, host: str) -> list[Finding]:
    """The job store cell serve opens (``db_url``, else the data folder's SQLite file), read without
    changing it, and for SQLite its folder and files (``cell.db*``: the database, its WAL, the cells'
    leases) this user's to write; and, for a ``host`` beyond loopback, an API key in it (cell serve
    refuses that host without one). The store's URL is shown with its password hidden."""
    if data_dir.exists() and not data_dir.is_dir():
        # its store-url could not be read ("Not a directory"): no other store would help
        return [Finding.fail("job store", f"none: --data-dir {data_dir} is not a folder", NOT_A_FOLDER_FIX)]
    try:
        url = service_store_url(data_dir, db_url)
    except StoreError as exc:
        return [Finding.fail("job store", str(exc), "run doctor with the service's store: --db URL or "
                             "CELL_DB (docs/deploy.md, section 6)")]
    shown = hide_password(url)
    database = sqlite_database(url)
    problem = sqlite_access_problem(database) if database is not None and database.parent.is_dir() else None
    if problem is not None:
        # read, the store looked fine; cell serve, which writes it, stopped at "unable to open database file"
        return [Finding.fail("job store", f"{shown}: {problem.found}", problem.fix + service_user_note())]
    try:
        state = inspect_store(url, STORE_CONNECT_TIMEOUT_S)
    except StoreError as exc:
        fix = ("stop cell serve, then restore the store from a backup (docs/deploy.md, section 9)"
               if isinstance(exc, StoreDamaged) or db_url is None else
               "check the URL, that the server runs and that this PC reaches it (pg_isready -h HOST)")
        return [Finding.fail("job store", str(exc), fix)]
    head = schema_head()
    if state is None:
        found = [Finding.ok("job store", f"{shown} is not made yet: cell serve makes it")]
    elif state.revisions and state.revisions != {head}:
        schema = ", ".join(sorted(state.revisions))
        text = (f"{shown}: schema {schema}, older than this software's {head}: the next cell serve migrates "
                f"it, {state.n_active_keys} API keys")
        if db_url is not None and sqlite_database(db_url) is None:
            # a shared store: a cell of the previous version on it refuses to start once it is migrated
            found = [Finding.warn("job store", text, "upgrade every cell on this store: stop them all, "
                                  "install this version on each, then start them (docs/deploy.md, "
                                  "'Updating')")]
        else:
            found = [Finding.ok("job store", text)]
    else:
        schema = ", ".join(sorted(state.revisions)) or "none yet, cell serve makes it"
        found = [Finding.ok("job store", f"{shown}: schema {schema}, {state.n_active_keys} API keys")]
    if not is_loopback(host):
        where = f"--data-dir {data_dir}" if db_url is None else "with this --db"
        if state is None or state.n_active_keys == 0:
            found.append(Finding.fail("remote access", f"cell serve refuses to listen on {host}, beyond this "
                                      "machine, with no API key in the store",
                                      f"create one first: cell keys create --role admin {where}"))
        else:
            found.append(Finding.ok("remote access", f"{host}: every route but /healthz needs one of the "
                                    f"{state.n_active_keys} API keys"))
    return found
