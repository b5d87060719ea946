"""Makes conf/ the package rlpipe.conf: Hydra reads it as pkg://rlpipe.conf once installed."""
