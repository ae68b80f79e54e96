"""The UKF family of Wang et al. 2019: the centralized UKF (ccl.py), UKF-DCL over serial chains (dcl.py) and the multilateration a lost node finds itself with (rejoin.py)."""
