"""Physics: the effect registry, the term language, units, presets and the fit library."""
