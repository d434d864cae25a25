"""trafficweaving: multimodal probabilistic model-based planning for human-robot traffic weaving.

A runnable, modern implementation of Schmerling, Leung, Vollprecht and Pavone, ICRA 2018.
"""

__version__ = "0.1.0"

from gymnasium.envs.registration import register as _register

_register(id="TrafficWeaving-v0", entry_point="trafficweaving.envs.traffic_weaving:TrafficWeavingEnv")
