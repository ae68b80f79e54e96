"""dNBP of Wan et al. 2014: Gaussian-mixture beliefs and messages (mixtures.py), the message schedule (schedule.py) and the node with its least-squares baseline (dnbp.py)."""
