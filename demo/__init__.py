"""`hapticlink demo`: the whole loop on one machine — assets built offline (`demo.assets`), the service, a simulated
robot touring unseen textures and a terminal feed (`demo.run`). The top of the house: it may import the service, the
drivers and the offline wing; only the benchmarks that time it import it."""
