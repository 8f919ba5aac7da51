"""evojax-motion: human-like, low-torque robot movements from an evolving primitive database.

Implements Park, Ra, Kim & Song (2008), *Imitation learning of robot movement using evolutionary
algorithm*, in JAX + MuJoCo. The modules follow the paper's pipeline (see docs/architecture.md);
import what you need from them, e.g. ``from evojax_motion.model.robot import load_robot``.
"""

__version__ = "0.1.0"
