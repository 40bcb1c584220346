"""What the tests compare between flights."""


def seeded_metrics(metrics: dict) -> dict:
    """A flight's metrics without its wall-clock figure (the real-time factor): what a seeded flight
    repeats exactly."""
    return {k: v for k, v in metrics.items() if k != "realtime_factor"}
