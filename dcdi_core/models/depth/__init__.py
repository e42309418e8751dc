"""Metric depth from one RGB image, behind one small interface
(``estimators.DepthEstimator``): the project's small network (``arch``,
``config``, ``train`` on the shared loop, ``export``) trained on the
factory's captures, and the large public estimators loaded from a
checkpoint on the user's disk (never downloaded here)."""
