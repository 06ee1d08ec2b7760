"""msdgrasp: frictional three-jaw grasping of a soft organ as a Gymnasium environment.

Subpackages (data flows one way: configs -> physics -> envs -> agents):

- :mod:`msdgrasp.physics`  meshes, the nonlinear viscoelastic mass-spring-damper tissue, the grasper
  and its Coulomb stick/slip contact, experiments and calibration. Plain arrays + numba kernels.
- :mod:`msdgrasp.envs`     Gymnasium environments (registered on import of ``msdgrasp``).
- :mod:`msdgrasp.agents`   training, baseline controllers, evaluation and the ``msdgrasp`` CLI.
"""

__version__ = "0.2.0"


def _register_envs() -> None:
    # Registration only stores entry-point strings: importing msdgrasp stays cheap (no numba). A missing
    # dependency (gymnasium) is an ImportError here, never a silently unregistered env.
    from .envs.registration import register_envs

    register_envs()


_register_envs()
