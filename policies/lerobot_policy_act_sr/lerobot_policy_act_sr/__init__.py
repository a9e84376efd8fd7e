"""ACT-SR LeRobot policy plugin (Sleeping Robots on LeRobot's ACT).

LeRobot 0.4.4 imports this package automatically (distribution name prefix ``lerobot_policy_``) before it
parses ``--policy.type``; importing it registers the policy configuration. The configuration, model and
processor modules arrive with the ACT-SR issue; this package already installs and is discovered.
"""

__version__ = "0.1.0"
