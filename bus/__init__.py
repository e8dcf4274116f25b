"""The middleware every process stands on, below the nodes: publish/subscribe and services over
ZeroMQ (:mod:`bus.pubsub`, :mod:`bus.services`), their context and discovery
(:mod:`bus.context`, :mod:`bus.registry`), CURVE security (:mod:`bus.security`), the node base
class and its start-up (:mod:`bus.node`, :mod:`bus.start`), MCAP bags (:mod:`bus.bag`,
:mod:`bus.bag_format`, :mod:`bus.bag_record_play`) and the inference node's client
(:mod:`bus.inference_client`). It imports only messages and the workcell; the device backends,
dataset, models and nodes import it."""
