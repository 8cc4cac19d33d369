"""Package data: the trained map estimator's weights (``estimator.pt``) and its model card.

Loaded by :meth:`torchbrdf.recovery.prior.Prior.default`; ``model_card.md`` says how they were
trained and how accurate they are on held-out samples.
"""
