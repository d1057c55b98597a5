"""The scenario families, one package each: the paper's (``porav``) and the peer systems brought onto our simulator
and yardstick (docs/design.md §10). A family's ``__init__.py`` declares it (``FAMILY``, a
``worldmodel.registry.Family``: plain data, cheap to import); its ``system`` module is what it runs (the
``registry.System`` interface: trainer, evaluation, Euro NCAP group, tables), imported when needed. Families never
import one another; what the peers share is ``common.py``.
"""
