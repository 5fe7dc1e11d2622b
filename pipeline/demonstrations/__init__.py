"""Making demonstrations: the scripted pilot and the interactive recorder."""
