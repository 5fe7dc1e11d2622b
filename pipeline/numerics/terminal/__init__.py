"""The terminal controller inside Goal: its design, and the tube ends fitted inside it."""
