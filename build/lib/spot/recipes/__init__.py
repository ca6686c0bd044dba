"""Local dataset recipes: build D4RL / Meta-World / robosuite style datasets in the real simulators.

They sit above ``spot.data`` (whose registry loads them by module name), ``spot.envs`` and
``spot.policy`` (SAC), which they use; ``spot.data`` imports none of those.
"""
