"""Evaluation: data sets (simulated trials, real bags), the loop that feeds messages to the core
(``feed``), replay of a bag with metrics and plots, corrupted inputs."""
