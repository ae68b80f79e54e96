"""Quadrotors and ground robots of Oliveros & Ashrafiuon 2023: their EKFs (filters.py) and the radio roles of EKF-CL, EKF-CI and EKF without CL (cl.py)."""
