"""Decentralized visual place recognition from full-image descriptors (issue 13).

Cieslewski and Scaramuzza's method: every frame becomes one L2-normalised
128-d descriptor (``models/descriptor``, run by :mod:`swarmrec.vpr.model`);
k-means centres trained on *other* data split the descriptor space into
``robots x clusters_per_robot`` cells, each owned by one robot
(:mod:`swarmrec.vpr.clusters`); a query goes only to the owner of its nearest
centre, which searches what was routed to it so far and then stores the query
(:mod:`swarmrec.vpr.index`). :mod:`swarmrec.vpr.evaluation` runs it offline
against a centralized search on the same descriptors, :mod:`swarmrec.vpr.balance`
assigns cells by load, :mod:`swarmrec.vpr.quantize` shrinks the descriptor
for the wire and :mod:`swarmrec.vpr.figures` draws the paper's Figs. 6 and 7.
See docs/vpr.md.

The modules are imported one by one (this file imports none of them) so that
the training script, which runs without faiss, can use :mod:`swarmrec.vpr.places`.
"""
