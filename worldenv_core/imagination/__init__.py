"""Imagination: the learned environment post-training acts in. `simulator` rolls the world model
forward from real frames under a policy's action chunks (with the kinematic next-state model and
its action maps), `env` wraps it with the reflector as reward and stopping rule into the batched
RL environment of LOOP, and `recording` writes imagined rollouts as MCAP episodes."""
