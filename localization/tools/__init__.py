"""The console scripts: ``localization-replay``, ``localization-simulate``, ``localization-demo``,
``localization-play`` (a DDS bag player for the pip-only environment), with shared argument types."""
