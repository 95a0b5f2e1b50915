"""The checks of one frame: could a load cause its change (gate), is it the scene's load (consistency), does it
agree with a controller's expected load (expected)."""
