"""The shadowed synthetic dataset: scenes, camera placement, generation, files and loading.

``loader`` is the one dataset reader used by every later stage; ``generate`` renders a
dataset from a Mitsuba XML scene (``mi-shadowgs generate``).
"""
