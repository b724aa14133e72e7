"""SYNTHETIC datasets: the `naturalistic`, `simulated` and `relational` generators, latent styles and the oracle.

Usage:
    degusta data generate naturalistic --out data/naturalistic
    degusta data generate simulated --out data/simulated
    degusta data generate relational --out data/relational

    from degusta_learn.synth import naturalistic, simulated, generate_dataset
    ds = naturalistic(seed=0)          # 199 participants x 5 arrangements, with ratings (in memory)

Every modelling choice is documented in docs/data.md and in the module docstrings: style.py (what a
latent style is), templates.py (how styles are drawn), realize.py (style -> arrangements),
ratings.py (jitter-study ratings), simulated.py (the paper's 72 experiments), oracle.py (the oracle: each
participant's own latent style), plausible.py (the rules every naturalistic table keeps; `--legacy` makes the
tables before them), posterior.py with posterior_model.py and posterior_prior.py (the achievable floor: the
posterior predictive under the generator; posterior_base.py holds what both floors share).
The second family, `relational` (placement rules, not slots; docs/generators.md): relational.py (the generator and
its options), relational_style.py, relational_habits.py (the draws), relational_realize.py (style -> arrangements),
relational_oracle.py and relational_posterior.py (its floor).
"""

from degusta_learn.synth.generate import GENERATORS, generate_dataset
from degusta_learn.synth.naturalistic import naturalistic, naturalistic_with_styles
from degusta_learn.synth.realize import expected_arrangement, sample_arrangement
from degusta_learn.synth.relational import RelationalOptions, relational_with_styles
from degusta_learn.synth.relational_realize import expected_relational, sample_relational
from degusta_learn.synth.relational_style import RelationalStyle, read_relational_styles, write_relational_styles
from degusta_learn.synth.simulated import simulated, simulated_episodes, simulated_with_styles
from degusta_learn.synth.style import STYLES_FILE, Noise, Setting, Slot, Style, read_styles, write_styles

__all__ = [
    "GENERATORS", "STYLES_FILE", "Noise", "RelationalOptions", "RelationalStyle", "Setting", "Slot", "Style",
    "expected_arrangement", "expected_relational", "generate_dataset", "naturalistic", "naturalistic_with_styles",
    "read_relational_styles", "read_styles", "relational_with_styles", "sample_arrangement", "sample_relational",
    "simulated", "simulated_episodes", "simulated_with_styles", "write_relational_styles", "write_styles",
]
