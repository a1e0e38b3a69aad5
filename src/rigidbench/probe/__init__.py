"""Probing Wan's transformer for physical state and position-subspace interventions (paper sections
5.2-5.3, appendix E): ``rigidbench probe extract|fit|intervene|report``. See docs/probing.md.

Light: the submodules import torch only where they need it; ``commands`` imports none of them."""
