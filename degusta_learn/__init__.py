"""degusta_learn: personalized multi-object rearrangement (table setting).

Reproduces DegustaBot's zero-shot visual prompting and adds learned baselines, LoRA fine-tuning of
small open VLMs and one evaluation harness. See README.md for the tour.
"""

__version__ = "0.1.0"
