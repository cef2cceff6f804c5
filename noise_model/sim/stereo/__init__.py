"""Physical D435 (work in progress): active-stereo simulation stages."""
