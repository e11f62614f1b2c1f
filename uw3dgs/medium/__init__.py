"""What the framework knows of an underwater medium, so that commands serve any plugin that has one: the image
formation contract (`formation.py`), the viewer's water control on it, and the field interface with its summary for
`uw-export` (`field.py`). Medium fields themselves are plugins (`fields/`)."""
