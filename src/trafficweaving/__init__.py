"""trafficweaving: multimodal probabilistic model-based planning for human-robot traffic weaving.

A runnable, modern implementation of Schmerling, Leung, Vollprecht and Pavone, ICRA 2018.
"""

__version__ = "0.1.0"
