"""The command line (neurogf-warp) and the demo it runs."""
