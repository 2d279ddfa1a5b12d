"""CSO post-training: R-SFT and SPO (paper Section 4)."""
