"""Pre-training (paper section 4.1–4.2): the ensemble RSSM with the HCU loss, its Lightning module, CLI and export.

See docs/pretraining.md. Fine-tuning reads the frozen export through `model.export.load_frozen`.
"""
