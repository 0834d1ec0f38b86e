"""The model workbench: compare a model with records, explain its error by named physical effects,
refit it with chosen effects (``agent.effects``). CLI: ``pmsm-agent model ...`` (``cli.py``)."""
