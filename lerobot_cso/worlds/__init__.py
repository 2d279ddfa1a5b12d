"""The worlds rollouts run in, one folder each (:mod:`lerobot_cso.worlds.base`: what a world is)."""
