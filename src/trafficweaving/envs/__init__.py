"""Gymnasium environments (registered on import of :mod:`trafficweaving`): ``TrafficWeaving-v0``,
the paper's scenario with the robot as the learning agent (:mod:`.traffic_weaving`)."""
