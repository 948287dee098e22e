# Rules of the study stage.
