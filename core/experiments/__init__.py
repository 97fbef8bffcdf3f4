"""Running many episodes: one episode, the resumable benchmark, the oracle labeller, pools."""
