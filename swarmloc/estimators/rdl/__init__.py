"""RDL: recursive decentralized localization after Luft, Schubert, Roumeliotis and Burgard
(IJRR 2018), with one-hop corrections (docs/rdl.md). The maths on factored cross-covariances
(`factors.py`) and the sans-I/O node that runs it over the radio (`node.py`)."""
