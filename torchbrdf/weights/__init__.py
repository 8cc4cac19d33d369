"""Package data: the trained map estimators' weights and their model cards.

``estimator.pt`` takes the flash image (``model_card.md``); ``estimator_ring4.pt`` the flash and
a ring of three lights, trained on the material families (``model_card_ring4.md``). Loaded by
:meth:`torchbrdf.recovery.prior.Prior.default`, which picks by the capture's light count; each
card says how they were trained and how accurate they are on held-out samples.
"""
