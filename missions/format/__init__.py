"""The mission file: the typed, frozen mission format (``schema``) and the YAML loader with its
error messages, overrides and bundled missions (``loader``)."""
