"""Errors that reach the user as one readable line.

Every error a user can cause (a bad file, a bad config value, an unstable simulation) derives from
:class:`Sync4DError`; ``train.py`` prints its message on one line and exits with code 2 instead of a
traceback (set ``HYDRA_FULL_ERROR=1`` to see the traceback).
"""

from __future__ import annotations


class Sync4DError(Exception):
    """Base class of errors caused by the user's input; the message names the input and the fix."""


class ConfigError(Sync4DError):
    """A configuration value is missing, unknown, of the wrong type or out of range."""


class RegistryError(ConfigError):
    """A component name is unknown or registered twice."""


class PluginImportError(Sync4DError):
    """A plugin package failed to import; the message names the plugin and the original error."""


class InputError(Sync4DError):
    """An input file or array is malformed (wrong shape, NaN, missing property, not the format)."""


class DataMissingError(Sync4DError):
    """An experiment needs data (e.g. ``../shared/data``) that is not on this machine."""


class SimulationUnstable(Sync4DError):
    """The requested time step violates the CFL bound and automatic sub-stepping is off."""


class SimulationDiverged(Sync4DError):
    """The simulation produced NaN/inf or particles left the grid."""
