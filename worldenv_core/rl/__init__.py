"""RL pieces the policy training and post-training share: the Laplace action distribution, ..."""
