"""``LearnToRun-v0``: the NIPS 2017 "Learning to Run" task on OpenSim 4.6 (the ``osim`` extra).

A planar musculoskeletal runner (9 degrees of freedom, 18 Thelen muscles: the
``gait9dof18musc`` model that osim-rl ships, CC BY 3.0, credits in ``assets/NOTICE``)
moves along x. Each action is one excitation in ``[0, 1]`` per muscle, held for one 0.01 s
step. The reward is the one the RAVE paper gives for this task (supplement, "Rewards for
Osim-based experiments"): ``r = max(d_l, d_r) + 0.5``, where ``d_l`` and ``d_r`` are how
far the left and right leg moved along x in the step; we measure a leg at its ankle (the
origin of the ``talus`` body). An episode terminates when the pelvis drops below 0.65 m
(a fall) and is truncated after 1,000 steps (10 s), as in the 2017 challenge.

Observation (36 numbers; the 2017 layout without its obstacle and psoas-strength entries):

====== =========================================================================
index  content
====== =========================================================================
0-2    pelvis tilt (rad), x, y (m)
3-5    their velocities
6-11   hip, knee and ankle angles, right then left (rad)
12-17  their angular velocities (rad/s)
18-21  centre of mass x, y and its velocity x, y
22-35  x, y of head, pelvis, torso, left toes, right toes, left talus, right talus
====== =========================================================================

Choices the sources leave open, made here:

- Reset noise. The model starts in its default pose with its muscles equilibrated. The
  six leg-joint angles get uniform noise in ``[-reset_noise_scale, reset_noise_scale]``
  rad drawn from the env's seed, so that episodes differ and a falling rate over many
  episodes is a rate; the 2017 start was fixed, its randomness came from obstacles.
- No obstacles (the 2017 challenge's difficulty 0).
- Integrator accuracy 1e-3 by default (``integrator_accuracy``); osim-rl's releases
  default to 5e-5. Under random excitations 1e-3 halves the cost of a step and gives the
  same episodes to three decimals of the return; ``benchmarks/learn_to_run_step.py``
  measures both.
"""

from __future__ import annotations

from importlib import resources

import gymnasium as gym
import numpy as np
import opensim
from gymnasium import spaces

from torchrl_rave.envs._opensim import set_excitations

# OpenSim opens its log file (opensim.log) in the directory of the first model it loads:
# the installed package's assets. Its messages still reach the console.
opensim.Logger.removeFileSink()

ENV_ID = "LearnToRun-v0"
MODEL_FILE = "gait9dof18musc.osim"
STEP_SECONDS = 0.01
MAX_EPISODE_STEPS = 1000
FALL_HEIGHT = 0.65
ALIVE_BONUS = 0.5
LEG_COORDINATES = (
    "hip_flexion_r",
    "knee_angle_r",
    "ankle_angle_r",
    "hip_flexion_l",
    "knee_angle_l",
    "ankle_angle_l",
)
PELVIS_COORDINATES = ("pelvis_tilt", "pelvis_tx", "pelvis_ty")
OBSERVED_BODIES = ("head", "pelvis", "torso", "toes_l", "toes_r", "talus_l", "talus_r")
# joint centres for drawing the runner: the origins of these bodies, as polylines
SKELETON = (
    ("head", "torso", "pelvis"),
    ("pelvis", "femur_r", "tibia_r", "talus_r", "calcn_r", "toes_r"),
    ("pelvis", "femur_l", "tibia_l", "talus_l", "calcn_l", "toes_l"),
)
# pelvis and leg coordinates with their speeds, centre of mass (x, y, vx, vy), body x, y
OBSERVATION_SIZE = 2 * (len(PELVIS_COORDINATES) + len(LEG_COORDINATES) + 2 + len(OBSERVED_BODIES))


def model_path() -> str:
    """Path of the packaged ``gait9dof18musc.osim`` model file."""
    return str(resources.files("torchrl_rave.envs").joinpath("assets", MODEL_FILE))


class LearnToRunEnv(gym.Env):
    """The 2017 Learning-to-Run task as a gymnasium env (see the module docstring).

    Args:
        integrator_accuracy (float): OpenSim's error tolerance of the variable-step
            integrator over each 0.01 s step.
        reset_noise_scale (float): half-width, in rad, of the uniform noise on the six
            leg-joint angles at reset.
        fall_height (float): the episode terminates once the pelvis is below this height (m).

    Examples:
        >>> import gymnasium as gym
        >>> import torchrl_rave.envs.learn_to_run  # registers LearnToRun-v0
        >>> env = gym.make("LearnToRun-v0")
        >>> obs, _ = env.reset(seed=0)
        >>> obs.shape, env.action_space.shape
        ((36,), (18,))
    """

    metadata = {"render_modes": []}

    def __init__(
        self,
        integrator_accuracy: float = 1e-3,
        reset_noise_scale: float = 0.01,
        fall_height: float = FALL_HEIGHT,
    ):
        if not integrator_accuracy > 0:
            raise ValueError(f"integrator_accuracy must be > 0, got {integrator_accuracy}")
        if not reset_noise_scale >= 0:
            raise ValueError(f"reset_noise_scale must be >= 0, got {reset_noise_scale}")
        self.integrator_accuracy = float(integrator_accuracy)
        self.reset_noise_scale = float(reset_noise_scale)
        self.fall_height = float(fall_height)

        opensim.Logger.setLevelString("error")  # else a report on every step, process-wide
        self._model = opensim.Model(model_path())
        self._model.initSystem()
        muscles = self._model.getMuscles()
        controller = opensim.PrescribedController()
        for i in range(muscles.getSize()):
            muscle = muscles.get(i)
            controller.addActuator(muscle)
            controller.prescribeControlForActuator(muscle.getName(), opensim.Constant(0.0))
        self._model.addController(controller)
        self._model.initSystem()
        functions = controller.get_ControlFunctions()
        self._excitations = [
            opensim.Constant.safeDownCast(functions.get(i)) for i in range(functions.getSize())
        ]
        self.muscle_names = tuple(muscles.get(i).getName() for i in range(muscles.getSize()))
        coordinates = self._model.getCoordinateSet()
        self._pelvis = [coordinates.get(name) for name in PELVIS_COORDINATES]
        self._legs = [coordinates.get(name) for name in LEG_COORDINATES]
        bodies = self._model.getBodySet()
        self._bodies = {
            name: bodies.get(name)
            for name in {*OBSERVED_BODIES, *(b for line in SKELETON for b in line)}
        }

        n = len(self._excitations)
        self.action_space = spaces.Box(0.0, 1.0, shape=(n,), dtype=np.float64)
        self.observation_space = spaces.Box(
            -np.inf, np.inf, shape=(OBSERVATION_SIZE,), dtype=np.float64
        )
        self._state = None
        self._manager = None
        self._steps = 0

    # the simulation
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        state = self._model.initializeState()
        noise = self.np_random.uniform(
            -self.reset_noise_scale, self.reset_noise_scale, size=len(self._legs)
        )
        for coordinate, delta in zip(self._legs, noise, strict=True):
            coordinate.setValue(state, coordinate.getDefaultValue() + float(delta))
        for excitation in self._excitations:
            excitation.setValue(0.0)
        self._model.equilibrateMuscles(state)
        state.setTime(0.0)
        self._state = state
        self._restart_integrator()
        self._steps = 0
        return self._observation(), {"pelvis_height": self.pelvis_height()}

    def step(self, action):
        if self._manager is None:
            raise RuntimeError("call reset() before step()")
        set_excitations(ENV_ID, action, self._excitations, self.action_space.shape)
        before = self.leg_x()
        self._steps += 1
        self._state = self._manager.integrate(STEP_SECONDS * self._steps)
        self._model.realizeVelocity(self._state)
        after = self.leg_x()
        reward = self.reward(before, after)
        height = self.pelvis_height()
        terminated = height < self.fall_height
        return self._observation(), reward, terminated, False, {"pelvis_height": height}

    def set_coordinates(self, values: dict[str, float]) -> None:
        """Sets joint coordinates (names as in the model: ``pelvis_tx``, ``knee_angle_l``,
        ...) in the current state and restarts the integrator from it; speeds and muscle
        states are kept. For chosen start poses, and for checking the kinematics."""
        if self._manager is None:
            raise RuntimeError("call reset() before set_coordinates()")
        coordinates = self._model.getCoordinateSet()
        for name, value in values.items():
            if not coordinates.contains(name):
                names = [coordinates.get(i).getName() for i in range(coordinates.getSize())]
                raise KeyError(f"no coordinate {name!r} in the model; it has {names}")
            coordinates.get(name).setValue(self._state, float(value))
        self._model.realizeVelocity(self._state)
        self._restart_integrator()

    def _restart_integrator(self) -> None:
        self._manager = opensim.Manager(self._model)
        self._manager.setIntegratorAccuracy(self.integrator_accuracy)
        self._manager.initialize(self._state)

    @staticmethod
    def reward(leg_x_before: np.ndarray, leg_x_after: np.ndarray) -> float:
        """``max(d_l, d_r) + 0.5`` from the legs' x before and after a step.

        Examples:
            >>> LearnToRunEnv.reward(np.array([0.10, 0.20]), np.array([0.13, 0.19]))
            0.53
        """
        return float(np.max(leg_x_after - leg_x_before)) + ALIVE_BONUS

    # reading the state
    def leg_x(self) -> np.ndarray:
        """x of the left and right ankle (talus origin), in that order."""
        return np.array([self._body_xy("talus_l")[0], self._body_xy("talus_r")[0]])

    def pelvis_height(self) -> float:
        return self._pelvis[2].getValue(self._state)

    def skeleton(self) -> list[np.ndarray]:
        """The runner's joint centres as polylines (torso; right leg; left leg), each an
        array of (x, y) rows, for drawing."""
        return [np.array([self._body_xy(b) for b in line]) for line in SKELETON]

    def _body_xy(self, name: str) -> tuple[float, float]:
        p = self._bodies[name].getPositionInGround(self._state)
        return p.get(0), p.get(1)

    def _observation(self) -> np.ndarray:
        s = self._state
        mass_centre = self._model.calcMassCenterPosition(s)
        mass_velocity = self._model.calcMassCenterVelocity(s)
        return np.array(
            [c.getValue(s) for c in self._pelvis]
            + [c.getSpeedValue(s) for c in self._pelvis]
            + [c.getValue(s) for c in self._legs]
            + [c.getSpeedValue(s) for c in self._legs]
            + [mass_centre.get(0), mass_centre.get(1), mass_velocity.get(0), mass_velocity.get(1)]
            + [v for b in OBSERVED_BODIES for v in self._body_xy(b)],
            dtype=np.float64,
        )


if ENV_ID not in gym.registry:
    gym.register(ENV_ID, entry_point=LearnToRunEnv, max_episode_steps=MAX_EPISODE_STEPS)
