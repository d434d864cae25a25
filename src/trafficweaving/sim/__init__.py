"""The simulation layer: one world (two cars, 0.1 s steps), the agent contract, simulated
drivers, and the human–human dataset generator that runs on them."""
