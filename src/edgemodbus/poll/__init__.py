"""Polling one slave on its line's worker thread.

* planner.py: items -> read blocks (pure, no I/O), per area and scan rate;
* schedule.py: the items' scan rates, the plan of a device, and each block's due time;
* poller.py: :class:`~edgemodbus.poll.poller.Poller`, the read cycle and fault handling;
* items.py: item state, the planned reads that decode it, and how results are stored;
* writes.py: write requests, and their execution with the slave's fallbacks;
* sink.py: what a poller reports to (its owner, which it never imports) and the delivery.

Its counters are :class:`edgemodbus.stats.DeviceStats`.

Nothing is imported here: ``config`` imports the planner's limits, and the poller
imports ``config``.
"""
