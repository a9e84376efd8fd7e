"""Protocol-specific analyses of docs/RESULTS.md, not installed with the package (``python -m experiments.<name>``
from the repository root); the reusable experiment drivers are :mod:`sr_imitation.experiments`."""
