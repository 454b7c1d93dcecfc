"""Training and evaluation: networks, trainers, quantizers, data, the synthetic engine, evaluation."""
