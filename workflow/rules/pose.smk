# Rules of the pose stage.
