"""Physics solvers (MPM, LBS, spring-mass) in Warp, the material-class registry and the effect registry."""
