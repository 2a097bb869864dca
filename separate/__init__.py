"""separate: optics, canonical projection, data synthesis, network, training, inference, baselines."""
