"""SUMO as a baseline and a map source: networks built with netconvert, runs through libsumo.

``netgen`` writes the 4-way geometry of ``scenarios/four-way-flows.toml`` as a SUMO
network (priority, all-way stop, actuated traffic light) and its demand; ``baseline``
runs SUMO on it and measures delay as crosspath does; ``from_sumo`` turns a
``.net.xml`` into a crosspath scenario. SUMO comes from the ``eclipse-sumo`` wheel (the
optional extra ``sumo``); :func:`services.sumo.netgen.sumo_home` finds it.
"""
