"""Force maps: a trace per pixel, fitted in chunks on an engine, written as maps."""
