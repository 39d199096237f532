"""The digital twin: a MuJoCo UR3 built from its DH table, tools, phantoms, tank, and the
simulated robot whose controller uses the nominal model while the true arm differs."""

from .phantoms import PhantomConfig
from .robot import RobotConfig, SimRobot
from .tools import ToolsConfig

__all__ = ["PhantomConfig", "RobotConfig", "SimRobot", "ToolsConfig"]
