# Rules of the imaging stage.
