"""Learning: the residual network and its training (the only stage that imports torch).

:mod:`.network` holds the torch MLP and its export to a CasADi graph; :mod:`.training` fits it
on a run's state observations with the one-step RK4 loss; :mod:`.model` is the trained model
and its directory (save, load).
Import the submodules directly; this package imports nothing so that ``learnest_codegen``
stays torch-free until a model is trained or loaded.
"""
