"""Choosing the demo: features, landmarks, labels, Q-model, learner, model selection, policies."""
