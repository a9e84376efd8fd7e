"""The ACT-SR substrate (``--substrate=act``, the default): the imitation stream on the ACT-SR plugin
(``lerobot_policy_act_sr``: the policy and its actor memory): the wake-sleep stream trainer, offline sleep
(``sr-sleep``), evaluation (``sr-eval``) and the MT-Joint oracle.

Importing this package registers the substrate's command and nothing heavier (no LeRobot): ``sr-train`` imports
:mod:`sr_imitation.substrates.act.cli` only when it runs this substrate."""

from sr_imitation.substrates.registry import SubstrateCommand, register_substrate


@register_substrate
class ACTCommand(SubstrateCommand):
    """ACT-SR on LeRobot datasets (the needle stream by default)."""

    name = "act"
    module = "sr_imitation.substrates.act.cli"
    parse_function = "parse_train_args"
    main_function = "train_main"
