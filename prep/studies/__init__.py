"""The studies of the data stage: measurements of prep's pieces, never part of them.

``render_bench`` (``kpcn bench render``: the path tracer's samples per second), ``stage_costs`` (what
computing features, decoding EXRs and the shard layouts cost) and ``report`` (the json + md + png report
every study writes, with its date, command and machine). A prep study imports only prep and the standard
library (never keras, torch or kpcn_keras); nothing else in prep imports a study.
"""
