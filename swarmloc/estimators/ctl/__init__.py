"""CSL-CTL of Wang et al. 2022: the majorization and its unscented covariance (majorization.py), and the CSL-CTL and IL-CTL nodes (csl_ctl.py)."""
