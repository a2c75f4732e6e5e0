"""Learners: the goal-conditioned DQN (:mod:`.dqn`) and Keulen's tabular Q-learning baseline (:mod:`.tabular`)."""
