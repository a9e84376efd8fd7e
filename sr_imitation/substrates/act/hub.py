"""``--policy.push_to_hub=true`` on ``sr-train``: the consolidated policy pushed with LeRobot's hub code.

Checked before the first gradient (:func:`check_push`): a ``policy.repo_id`` is required and the Hugging Face Hub
must be reachable with a token (``HfApi().whoami()``); offline (``HF_HUB_OFFLINE=1``, or no network as on the
project's machines) it is one line naming the repo, so hours of training never end in a failed push. After the
stream's last stage (:func:`push_policy`): the final checkpoint's ``pretrained_model/`` (weights, config,
processors) with LeRobot's model card (``PreTrainedPolicy.generate_model_card``) is uploaded in one commit, as
``PreTrainedPolicy.push_model_to_hub`` does for ``lerobot-train`` (which needs a ``TrainPipelineConfig`` this
stream does not have).
"""

from __future__ import annotations

import logging
import shutil
import tempfile
from pathlib import Path
from typing import Any

logger = logging.getLogger(__name__)


def check_push(policy_cfg: Any) -> None:
    """Refuse an impossible push before anything is trained (see the module docstring)."""
    if not policy_cfg.push_to_hub:
        return
    repo = policy_cfg.repo_id
    if not repo:
        raise ValueError("policy.push_to_hub=true needs --policy.repo_id=<user>/<name> (or pass "
                         "--policy.push_to_hub=false)")
    from huggingface_hub import HfApi, constants  # noqa: PLC0415

    if constants.HF_HUB_OFFLINE:
        raise ValueError(f"policy.push_to_hub: cannot push {repo}: the Hugging Face Hub is switched off here "
                         "(HF_HUB_OFFLINE=1); pass --policy.push_to_hub=false, or push later")
    try:
        HfApi().whoami()
    except Exception as exc:  # noqa: BLE001 - network, token and HTTP errors all mean "cannot push"
        reason = " ".join(str(exc).split())[:200]
        raise ValueError(f"policy.push_to_hub: cannot push {repo}: the Hub is not reachable with a token "
                         f"({type(exc).__name__}: {reason}); pass --policy.push_to_hub=false, or push later") from None


def push_policy(policy: Any, pretrained: Path, dataset_ids: list[str]) -> str:
    """Upload ``pretrained`` (a LeRobot ``pretrained_model/`` directory) with a model card to ``policy.config``'s
    ``repo_id``; returns the repo URL."""
    from huggingface_hub import HfApi  # noqa: PLC0415

    cfg = policy.config
    api = HfApi()
    repo_id = api.create_repo(repo_id=cfg.repo_id, private=cfg.private, exist_ok=True).repo_id
    with tempfile.TemporaryDirectory(ignore_cleanup_errors=True) as tmp:
        folder = Path(tmp) / "model"
        shutil.copytree(pretrained, folder)
        card = policy.generate_model_card(", ".join(dataset_ids), cfg.type, cfg.license, cfg.tags)
        card.save(str(folder / "README.md"))
        info = api.upload_folder(repo_id=repo_id, repo_type="model", folder_path=folder,
                                 commit_message="Upload the consolidated Sleeping Robots policy",
                                 allow_patterns=["*.safetensors", "*.json", "*.md"])
    url = str(getattr(info, "repo_url", repo_id))
    logger.info("consolidated policy pushed to %s", url)
    return url
