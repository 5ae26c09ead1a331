"""franky-sim (MuJoCo) with the faults a real Franka control unit raises, for the Franka backend's tests.

franky-sim speaks the robot's protocol but simulates no error state: its automatic error recovery always
succeeds and nothing ever aborts a motion. This peer is franky-sim's own simulation and server with what
the control unit does on a fault, on the same wire:

- ``reflex NAME...`` (names of libfranka's ``Errors`` flags, e.g. ``cartesian_reflex``): the robot holds
  its last commanded joints, reports robot mode ``Reflex`` with the flags in both ``current_errors`` and
  ``last_motion_errors`` (the wire's ``errors`` and ``reflex_reason``), and answers the running Move with
  ``ReflexAborted``, which libfranka turns into a ``ControlException`` naming the flags.
- ``user-stop``: the user stop is pressed: mode ``UserStopped`` and the running Move answered
  ``EmergencyAborted``; automatic error recovery is refused (``CommandNotPossibleRejected``, the
  peer's choice of the refusals libfranka knows) until ``release``.
- ``release``: the user stop is released: mode ``Idle``, the errors stay until recovered.

While faulted, a Move is aborted (``Aborted``). Automatic error recovery clears the errors and returns to
``Idle``. Commands come one per line on stdin; each is acknowledged on stdout with ``done <line>`` once the
simulation loop has applied it, so a test knows the fault is in place.

    python -m tests.franky_fault_sim --hostname 127.0.0.N [--q q1,...,q7]
"""

from __future__ import annotations

import argparse
import queue
import sys
import threading
from collections.abc import Sequence

from franky_sim import DEFAULT_INITIAL_JOINT_POS, FrankaRobotServer, SimulationServer
from franky_sim.franka_robot_protocol import (
    AutomaticErrorRecoveryCommand,
    AutomaticErrorRecoveryStatus,
    BaseCommand,
    MoveCommandControllerMode,
    MoveCommandMotionGeneratorMode,
    MoveStatus,
    RobotCommand,
    RobotMode,
)
from franky_sim.franka_robot_state import FrankaRobotState
from franky_sim.mujoco_simulator import MujocoSimulator

# libfranka's research-interface error flags, in wire order (the 41 booleans of ``errors``/``reflex_reason``)
ERROR_FLAGS = (
    "joint_position_limits_violation", "cartesian_position_limits_violation",
    "self_collision_avoidance_violation", "joint_velocity_violation", "cartesian_velocity_violation",
    "force_control_safety_violation", "joint_reflex", "cartesian_reflex",
    "max_goal_pose_deviation_violation", "max_path_pose_deviation_violation",
    "cartesian_velocity_profile_safety_violation", "joint_position_motion_generator_start_pose_invalid",
    "joint_motion_generator_position_limits_violation", "joint_motion_generator_velocity_limits_violation",
    "joint_motion_generator_velocity_discontinuity", "joint_motion_generator_acceleration_discontinuity",
    "cartesian_position_motion_generator_start_pose_invalid",
    "cartesian_motion_generator_elbow_limit_violation",
    "cartesian_motion_generator_velocity_limits_violation",
    "cartesian_motion_generator_velocity_discontinuity",
    "cartesian_motion_generator_acceleration_discontinuity",
    "cartesian_motion_generator_elbow_sign_inconsistent", "cartesian_motion_generator_start_elbow_invalid",
    "cartesian_motion_generator_joint_position_limits_violation",
    "cartesian_motion_generator_joint_velocity_limits_violation",
    "cartesian_motion_generator_joint_velocity_discontinuity",
    "cartesian_motion_generator_joint_acceleration_discontinuity",
    "cartesian_position_motion_generator_invalid_frame",
    "force_controller_desired_force_tolerance_violation", "controller_torque_discontinuity",
    "start_elbow_sign_inconsistent", "communication_constraints_violation", "power_limit_violation",
    "joint_p2p_insufficient_torque_for_planning", "tau_j_range_violation", "instability_detected",
    "joint_move_in_wrong_direction", "cartesian_spline_motion_generator_violation",
    "joint_via_motion_generator_planning_joint_limit_violation", "base_acceleration_initialization_timeout",
    "base_acceleration_invalid_reading",
)
NO_ERRORS = (False,) * len(ERROR_FLAGS)


def error_flags(names: Sequence[str]) -> tuple[bool, ...]:
    unknown = set(names) - set(ERROR_FLAGS)
    if unknown:
        raise ValueError(f"unknown error flags: {sorted(unknown)}")
    return tuple(flag in names for flag in ERROR_FLAGS)


class FaultyRobotServer(FrankaRobotServer):
    """franky-sim's robot server with an error state (see the module docstring)."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        self.mode = RobotMode.kIdle
        self.errors = NO_ERRORS
        self.reflex_reason = NO_ERRORS
        self.user_stop_pressed = False
        super().__init__(*args, **kwargs)
        # franky-sim builds its command table inside __init__ without a hook: replace its recovery handler
        table = self._FrankaServer__command_class_map
        table[RobotCommand.kAutomaticErrorRecovery] = RecoveryCommand

    @property
    def faulted(self) -> bool:
        return self.mode in (RobotMode.kReflex, RobotMode.kUserStopped) or any(self.errors)

    def start_motion(self, controller_mode: MoveCommandControllerMode,
                     motion_generator_mode: MoveCommandMotionGeneratorMode, motion_id: int) -> None:
        if self.faulted:
            raise RuntimeError("the robot is faulted")  # MoveCommand.handle answers Aborted
        super().start_motion(controller_mode, motion_generator_mode, motion_id)

    @property
    def robot_state(self) -> FrankaRobotState:
        state = super().robot_state
        if not self.faulted:
            return state.replace(reflex_reason=self.reflex_reason)
        return state.replace(robot_mode=self.mode, errors=self.errors, reflex_reason=self.reflex_reason)

    def _abort_motion(self, status: MoveStatus) -> None:
        """Hold where the arm is and answer the running Move with ``status``, as the control unit does."""
        motion_id = self.current_motion_id
        self.stop_motion(send_preemption_signal=False)
        if motion_id:
            BaseCommand.send_response(self._tcp_socket, RobotCommand.kMove, motion_id, status)
            self.reset_current_motion_id()

    def apply(self, line: str) -> None:
        """One stdin command (see the module docstring)."""
        word, *names = line.split()
        if word == "reflex":
            self.errors = self.reflex_reason = error_flags(names)
            self.mode = RobotMode.kReflex
            self._abort_motion(MoveStatus.kReflexAborted)
        elif word == "user-stop":
            self.user_stop_pressed = True
            self.mode = RobotMode.kUserStopped
            self._abort_motion(MoveStatus.kEmergencyAborted)
        elif word == "release":
            self.user_stop_pressed = False
            self.mode = RobotMode.kIdle
        else:
            raise ValueError(f"unknown command {line!r}")

    def recover(self) -> AutomaticErrorRecoveryStatus:
        if self.user_stop_pressed:
            return AutomaticErrorRecoveryStatus.kCommandNotPossibleRejected
        self.mode = RobotMode.kIdle
        self.errors = NO_ERRORS
        return AutomaticErrorRecoveryStatus.kSuccess


class RecoveryCommand(AutomaticErrorRecoveryCommand):
    """Automatic error recovery that clears the peer's errors (refused while the user stop is pressed)."""

    def handle(self, server: FaultyRobotServer) -> None:
        self.reply(server.recover())


class FaultySimulationServer(SimulationServer):
    """franky-sim's simulation server with a :class:`FaultyRobotServer` per robot."""

    def init(self) -> None:
        for robot in self.sim.robots:
            server = FaultyRobotServer(robot, self._remaining_hostname_candidates)
            server.init()
            self.robot_servers.append(server)
        self.sim.start()


def read_commands(commands: queue.Queue[str]) -> None:
    for line in sys.stdin:
        if line.strip():
            commands.put(line.strip())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hostname", required=True)
    parser.add_argument("--q", default=",".join(map(str, DEFAULT_INITIAL_JOINT_POS)),
                        help="initial joint positions [rad], comma-separated")
    args = parser.parse_args()
    commands: queue.Queue[str] = queue.Queue()
    threading.Thread(target=read_commands, args=(commands,), daemon=True).start()
    with MujocoSimulator() as sim:
        robot = sim.add_robot(initial_q=[float(v) for v in args.q.split(",")])
        with FaultySimulationServer(sim, hostname_candidates=[args.hostname]) as server:
            print(f"Connect to the server using '{robot.hostname}' as the robot IP address", flush=True)
            robot_server = server.robot_servers[0]
            assert isinstance(robot_server, FaultyRobotServer)
            while True:
                server.run_once()
                while not commands.empty():
                    line = commands.get()
                    robot_server.apply(line)
                    print(f"done {line}", flush=True)


if __name__ == "__main__":
    main()
