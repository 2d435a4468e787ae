"""Accuracy of a model against exact or solver geodesics and the heat method."""
