"""Which safety tests fail when a safety function is taken out of the guard.

Each mutant below removes one function from the guard (``cell/safety``). For the unmutated code and for
each mutant, the working tree (tracked and untracked files, with the compiled kernels) is copied to a
temporary folder, the mutant's edit is applied to the copy (the text it replaces must occur exactly
once), and the safety test files (``TEST_FILES``, or ``--files``) run there with the copy first on the
import path (checked: the copy's ``cell.safety.guard`` is the one imported). The working tree itself is
never modified. With ``--soak N`` the safety soak (``benchmarks/safety_soak.py``) also runs in each copy
with N commands per robot.

Prints one line per mutant, then one line of JSON: the tests that failed for each (the unmutated copy must
have none) and whether every mutant failed at least one test. Exits 1 when one did not.

    .venv/bin/python benchmarks/safety_mutants.py [--soak N] [--only NAME ...] [--files TEST_FILE ...]
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from options import BenchmarkParser, at_least, first_paragraph

REPO = Path(__file__).resolve().parents[1]
TEST_FILES = ("tests/test_safety_guard.py", "tests/test_safety_properties.py",
              "tests/test_safety_scenarios.py", "tests/test_collision_motion.py")
RUN_TIMEOUT_S = 900.0
GUARD = "cell/safety/guard.py"
COLLISION = "cell/safety/collision.py"


@dataclass(frozen=True)
class Mutant:
    """An edit to one file: ``old`` (which must occur exactly once) becomes ``new``."""

    name: str
    what: str
    path: str
    old: str
    new: str


MUTANTS = (
    Mutant("no-barrier-projection", "streamed twists are not projected into the barrier planes", GUARD,
           "v, planes = self.barriers.project_twist(v, T[:3, 3], points,\n" + " " * 48
           + "s.tcp_max_linear_mps + s.tcp_max_angular_rps * lever)", "planes: list[str] = []"),
    Mutant("no-braking-check", "the stop that would follow a streamed twist is not checked", GUARD,
           "unsafe = self._braking_violation(state, ik)", "unsafe = None"),
    Mutant("no-joint-overrun-stop", "a joint carried towards its limit faster than the IK predicted is not "
           "stopped", GUARD, "overrun = self._joint_overrun(state)", "overrun = None"),
    Mutant("no-barrier-check-of-moves", "trajectory samples are not checked against the barrier planes",
           GUARD, "reason = self.barriers.first_violation(self.guarded_points(T), GUARDED_POINTS, floor)\n",
           "reason = None\n"),
    Mutant("no-collision-check-of-twists", "the motion predicted ahead of a streamed twist is not checked "
           "for collisions", GUARD, "hit = self._collision_ahead(state.q, ik(v))", "hit = None"),
    Mutant("no-path-check-of-twists", "only the configuration predicted ahead of a streamed twist is checked "
           "for collisions, not the arm's way to it", GUARD, "check_motion(q, q_pred)",
           "check_motion(q_pred, q_pred)"),
    Mutant("no-bound-since-the-reference", "a path is cleared by the distances kept from an earlier "
           "configuration without the bound on how far the arm moved since", COLLISION,
           "np.maximum(np.abs(q_from - ref.q), np.abs(q_to - ref.q))", "np.zeros_like(ref.q)"),
    Mutant("no-new-roi-for-the-way-ahead", "the distances kept for the arm's way ahead outlive a new ROI",
           COLLISION, "if ref is None or ref.roi is not self._roi:", "if ref is None:"),
    Mutant("every-capsule-axial", "a joint's turn counts as keeping the distance of every capsule it turns "
           "(not only of one on its axis)", COLLISION, "axial[i] = on_z & (axis_frame == c.frame)",
           "axial[i] = c.frame <= axis_frame"),
    Mutant("one-joint-pairs-never-touch", "two link capsules whose distance one joint changes are left "
           "unchecked without the proof that they stay apart over its range", COLLISION,
           "if np.min(d[:-1] + d[1:] - lever[j] * step) / 2.0 > 2.0 * PATH_CONTACT_M:", "if True:"),
    Mutant("no-collision-check-of-moves", "trajectories are not checked for collisions", GUARD,
           "hit = self.collision.check_path(q, self._safety.collision.trajectory_step_rad)", "hit = None"),
    Mutant("no-fcl", "FCL never reports a contact (the collision world finds none in a configuration)",
           COLLISION, "return fcl.collide(a, b, self._request, fcl.CollisionResult()) > 0", "return False"),
    Mutant("no-fcl-distance", "FCL's distance never reports bodies close (a path check finds no contact)",
           COLLISION, "return float(fcl.distance(a, b, self._distance_request, fcl.DistanceResult()))",
           "return float(np.inf)"),
    Mutant("no-sweep-bound-of-moves", "a move's path is clear when its checked configurations are (the "
           "motion between them is not bounded)", COLLISION, "open_ = da + db <= need",
           "open_ = np.zeros(len(need), dtype=bool)"),
    Mutant("no-joint-clamp-of-twists", "streamed twists are not slowed down before a joint's margin", GUARD,
           "scale = float(np.min(np.minimum(allowed[moving] / np.abs(qd[moving]), 1.0)))", "scale = 1.0"),
    Mutant("no-joint-acceleration-limit-of-twists", "a streamed twist may ask a joint to change speed faster "
           "than the robot can", GUARD,
           "share = self._joint_rate_share(state.qd, ik(np.asarray(snapshot[0])), qd)", "share = 1.0"),
    Mutant("no-joint-check-of-moves", "trajectory samples are not checked against the joint margins", GUARD,
           "outside = np.nonzero(np.any((q[1:] < self._q_lo) | (q[1:] > self._q_hi), axis=1))[0]",
           "outside = np.zeros(0, dtype=int)"),
    Mutant("no-watchdog", "the guard's tick consults no watchdog", GUARD,
           "for reason in (self.watchdog.tick(now), self.watchdog.perception(now, perception_time_s)):",
           "for reason in ():"),
    Mutant("no-late-loop-stop", "late control ticks are not counted", GUARD,
           "for reason in (self.watchdog.tick(now), ", "for reason in (None, "),
    Mutant("no-stale-perception-stop", "the age of perception is not judged", GUARD,
           "self.watchdog.perception(now, perception_time_s)):", "None):"),
)


def _copy_tree(dest: Path) -> None:
    """The working tree as it is (tracked and untracked files that git does not ignore) plus the compiled
    kernels, which git ignores."""
    listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                            cwd=REPO, check=True, capture_output=True).stdout.decode().split("\0")
    kernels = [str(p.relative_to(REPO)) for p in (REPO / "cell").rglob("*.so")]
    for rel in [f for f in listed if f] + kernels:
        src = REPO / rel
        if src.is_file():
            (dest / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / rel)


def _apply(root: Path, mutant: Mutant) -> None:
    path = root / mutant.path
    text = path.read_text()
    count = text.count(mutant.old)
    if count != 1:
        raise SystemExit(f"mutant {mutant.name}: the text to replace occurs {count} times in {mutant.path} "
                         "(expected once); update the mutant to the code")
    path.write_text(text.replace(mutant.old, mutant.new))


def _run(root: Path, args: list[str]) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(root)}
    return subprocess.run([sys.executable, *args], cwd=root, env=env, capture_output=True, text=True,
                          timeout=RUN_TIMEOUT_S, check=False)


def _failed_tests(junit: Path) -> tuple[list[str], int]:
    """The ids of the tests that failed or errored, and how many ran."""
    suite = ET.parse(junit).getroot()
    failed, ran = [], 0
    for case in suite.iter("testcase"):
        ran += 1
        if case.find("failure") is not None or case.find("error") is not None:
            module = case.get("classname", "").rsplit(".", 1)[-1]
            failed.append(f"{module}::{case.get('name')}")
    return failed, ran


def check(mutant: Mutant | None, files: list[str], soak: int) -> dict[str, Any]:
    """Copy the tree, apply ``mutant`` (None: the code as it is), run the test ``files`` (and the soak)."""
    with tempfile.TemporaryDirectory(prefix="safety-mutant-") as tmp:
        root = Path(tmp)
        _copy_tree(root)
        if mutant is not None:
            _apply(root, mutant)
        where = _run(root, ["-c", "import cell.safety.guard as g; print(g.__file__)"]).stdout.strip()
        if not where.startswith(str(root)):
            raise SystemExit(f"the copy's guard is not the one imported ({where!r}); check PYTHONPATH")
        t0 = time.perf_counter()
        junit = root / "junit.xml"
        tests = _run(root, ["-m", "pytest", "-q", "-p", "no:cacheprovider", f"--junitxml={junit}", *files])
        if not junit.exists():
            raise SystemExit(f"pytest did not run:\n{tests.stdout}\n{tests.stderr}")
        failed, ran = _failed_tests(junit)
        result: dict[str, Any] = {"tests_run": ran, "failed": failed,
                                  "tests_s": round(time.perf_counter() - t0, 1)}
        if soak:
            out = _run(root, ["benchmarks/safety_soak.py", "--commands", str(soak)])
            if out.returncode != 0:
                raise SystemExit(f"the soak failed:\n{out.stderr}")
            figures = json.loads(out.stdout.strip().splitlines()[-1])
            result["soak"] = {r["robot"]: {"commands": r["commands"], "refused": r["refused_total"],
                                           "breaches": {k: v for k, v in r["breaches"].items() if v}}
                              for r in figures["robots"]}
    return result


def main() -> None:
    parser = BenchmarkParser(description=first_paragraph(__doc__))
    parser.add_argument("--soak", type=at_least(0), default=0, metavar="N",
                        help="also run the safety soak in each copy with N commands per robot")
    parser.add_argument("--only", action="append", choices=[m.name for m in MUTANTS],
                        help="check only this mutant (repeatable)")
    parser.add_argument("--files", nargs="+", default=list(TEST_FILES),
                        help=f"test files to run (default: {' '.join(TEST_FILES)})")
    args = parser.parse_args()
    baseline = check(None, args.files, args.soak)
    print(f"{'unmutated':30s} {len(baseline['failed'])} of {baseline['tests_run']} tests failed", flush=True)
    report = []
    for mutant in MUTANTS:
        if args.only and mutant.name not in args.only:
            continue
        r = check(mutant, args.files, args.soak)
        report.append({"name": mutant.name, "what": mutant.what, "file": mutant.path,
                       "caught": bool(r["failed"]), **r})
        print(f"{mutant.name:30s} {len(r['failed'])} of {r['tests_run']} tests failed", flush=True)
    all_caught = all(m["caught"] for m in report) and not baseline["failed"]
    print(json.dumps({"test_files": args.files, "unmutated": baseline, "mutants": report,
                      "all_caught": all_caught}))
    sys.exit(0 if all_caught else 1)


if __name__ == "__main__":
    main()
