"""What the paper's family runs (the ``System`` of worldmodel/registry.py). Its agents train in train_agent's own
loop on the world model, so it declares no learners and has no trainer here."""

from __future__ import annotations

NCAP_REWARD = "r2"  # the reward its env reports on the Euro NCAP bank


def evaluate(cfg) -> dict:
    from .evaluation import evaluate as run

    return run(cfg)


def ncap_group(cfg, takeover_ttc_s: float) -> tuple:
    """The paper's policies take over at ``takeover_ttc_s``, at the world model's step length (the paper's 1/15 s
    when the experiment's env is another family's)."""
    from ...config import validate
    from ...policies import porav_policies

    typed = validate(cfg)
    step_s = typed.env.step_s if typed.env.family == "porav" else 1.0 / 15.0
    return step_s, porav_policies(cfg), NCAP_REWARD, takeover_ttc_s


def render_tables(rows: list[dict], settings: dict) -> str:
    from ... import report

    return report.tables_markdown(rows)
