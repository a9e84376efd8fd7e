"""The imitation substrate on the ACT-SR plugin (``lerobot_policy_act_sr``: the policy and its actor memory): the
wake-sleep stream trainer, offline sleep and evaluation."""
