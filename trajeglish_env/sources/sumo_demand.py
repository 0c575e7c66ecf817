"""Random traffic demand for a SUMO network: vehicle types, vehicle/bicycle trips and pedestrian walks.

The network starts populated (vehicles and pedestrians spread over it at time zero), then vehicles
keep entering from, and leave through, the network's fringe edges while pedestrians appear on random
sidewalks, so that after a short warm-up the traffic is in a steady state. Vehicle sizes, class mix,
densities and driver parameters are drawn per seed; SUMO routes the trips itself at insertion.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from trajeglish_env.scenario import AgentKind
from trajeglish_env.sources.sumo_net import SumoNet

# (vClass, (length range), (width range), speedFactor mean) per vehicle type family.
_VEHICLE_FAMILIES = {
    "car": ("passenger", (3.8, 5.2), (1.7, 2.0), 1.0),
    "truck": ("truck", (6.0, 9.0), (2.2, 2.5), 0.9),
    "bus": ("bus", (10.0, 13.0), (2.5, 2.6), 0.85),
    "bike": ("bicycle", (1.6, 1.9), (0.6, 0.8), 1.0),
    "ped": ("pedestrian", (0.45, 0.6), (0.5, 0.7), 1.0),
}
_FAMILY_KIND = {
    "car": AgentKind.VEHICLE,
    "truck": AgentKind.VEHICLE,
    "bus": AgentKind.VEHICLE,
    "bike": AgentKind.CYCLIST,
    "ped": AgentKind.PEDESTRIAN,
}


@dataclass(frozen=True)
class AgentType:
    """A SUMO vType drawn for one simulation, with the box size reported in the scenes."""

    type_id: str
    family: str
    length: float
    width: float

    @property
    def kind(self) -> AgentKind:
        return _FAMILY_KIND[self.family]


@dataclass(frozen=True)
class DemandConfig:
    """Ranges the per-seed demand is drawn from (densities per lane or sidewalk km, rates per fringe edge)."""

    vehicles_per_lane_km: tuple[float, float] = (8.0, 18.0)
    pedestrians_per_km: tuple[float, float] = (8.0, 20.0)
    inflow_per_fringe_edge_per_s: tuple[float, float] = (0.04, 0.1)
    pedestrian_inflow_per_km_per_s: tuple[float, float] = (0.03, 0.08)
    bicycle_share: tuple[float, float] = (0.08, 0.25)
    truck_share: tuple[float, float] = (0.0, 0.08)
    bus_share: tuple[float, float] = (0.0, 0.04)
    types_per_family: int = 3


def draw_agent_types(rng: np.random.Generator, config: DemandConfig) -> list[AgentType]:
    """Random vTypes: ``types_per_family`` sizes for each family (car, truck, bus, bike, pedestrian)."""
    types = []
    for family, (_, lengths, widths, _) in _VEHICLE_FAMILIES.items():
        for k in range(config.types_per_family):
            length, width = rng.uniform(*lengths), rng.uniform(*widths)
            types.append(AgentType(f"{family}{k}", family, round(float(length), 2), round(float(width), 2)))
    return types


def _vtype_xml(agent_type: AgentType, rng: np.random.Generator) -> str:
    v_class, _, _, speed_mean = _VEHICLE_FAMILIES[agent_type.family]
    attrs = {
        "id": agent_type.type_id,
        "vClass": v_class,
        "length": f"{agent_type.length:.2f}",
        "width": f"{agent_type.width:.2f}",
    }
    if agent_type.family == "ped":
        attrs["speed"] = f"{rng.uniform(1.1, 1.5):.2f}"  # desired walking speed (m/s)
    else:
        attrs["speedFactor"] = f"normc({speed_mean:.2f},{rng.uniform(0.05, 0.15):.2f},0.5,1.5)"
        attrs["sigma"] = f"{rng.uniform(0.2, 0.6):.2f}"
        attrs["latAlignment"] = "center"  # "right" makes bicycles hop sideways where lane widths change
        attrs["minGapLat"] = f"{rng.uniform(0.4, 0.8):.2f}"
        attrs["lcSublane"] = f"{rng.uniform(0.5, 1.5):.2f}"
        # Ask for no sideways moves at standstill and at most 0.1 m lateral per metre forward (SUMO's
        # heading follows lateral motion). SUMO ignores this for urgent lane changes, so the scene
        # source also limits headings itself (sumo_sim.vehicle_boxes).
        attrs["lcMaxSpeedLatStanding"] = "0"
        attrs["lcMaxSpeedLatFactor"] = "0.1"
    return "<vType " + " ".join(f"{k}={quoteattr(v)}" for k, v in attrs.items()) + "/>"


def _arrival_times(rng: np.random.Generator, rate: float, duration: float) -> np.ndarray:
    """Poisson arrival times in [0, duration) for a process of ``rate`` per second."""
    return np.sort(rng.uniform(0.0, duration, size=rng.poisson(rate * duration)))


def _vehicle_trips(
    net: SumoNet, rng: np.random.Generator, duration: float, config: DemandConfig, types: list[AgentType]
) -> list[tuple[float, str]]:
    """(depart, XML) of every vehicle and bicycle trip: the initial population, then the fringe inflow."""
    # Vehicles start only on edges they can drive on from (SUMO builds no turnarounds here, so an edge
    # into a dead end, like the network's exits, would trap them).
    onward = {c.from_edge for c in net.connections if c.via and c.to_edge in net.edges}
    roads = [e for e in net.edges.values() if e.vehicle_lanes and e.edge_id in onward]
    if not roads:
        raise ValueError("SUMO network has no drivable vehicle lanes: cannot generate urban demand")
    fringe_in, fringe_out = net.fringe_edges()
    road_ids = np.array([e.edge_id for e in roads])
    lane_metres = np.array([e.length * len(e.vehicle_lanes) for e in roads])
    sources = np.array(fringe_in) if fringe_in else road_ids
    sinks = np.array(fringe_out) if fringe_out else road_ids
    shares = [
        rng.uniform(*config.truck_share),
        rng.uniform(*config.bus_share),
        rng.uniform(*config.bicycle_share),
    ]
    family_p = np.array([1.0 - sum(shares), *shares])
    families = np.array(["car", "truck", "bus", "bike"])
    by_family = {f: [t.type_id for t in types if t.family == f] for f in families}

    n_initial = int(round(rng.uniform(*config.vehicles_per_lane_km) * lane_metres.sum() / 1000.0))
    starts = rng.choice(road_ids, n_initial, p=lane_metres / lane_metres.sum())
    routes = [
        (
            float(depart),
            f'from="{start}" to="{rng.choice(sinks)}" departPos="random_free" departLane="random"',
        )
        for depart, start in zip(rng.uniform(0.0, 2.0, n_initial), starts, strict=True)
    ]
    inflow = rng.uniform(*config.inflow_per_fringe_edge_per_s) * len(sources)
    routes += [
        (
            float(depart),
            f'from="{rng.choice(sources)}" to="{rng.choice(sinks)}" departPos="base" departLane="best"',
        )
        for depart in _arrival_times(rng, inflow, duration)
    ]
    trips = []
    for i, (depart, route) in enumerate(sorted(routes)):
        vtype = rng.choice(by_family[str(rng.choice(families, p=family_p))])
        trips.append(
            (depart, f'<trip id="v{i}" type="{vtype}" depart="{depart:.1f}" {route} departSpeed="desired"/>')
        )
    return trips


def _pedestrian_walks(
    net: SumoNet, rng: np.random.Generator, duration: float, config: DemandConfig, types: list[AgentType]
) -> list[tuple[float, str]]:
    """(depart, XML) of every pedestrian: walks between random sidewalk points of two edges."""
    walks = [e for e in net.edges.values() if e.has_sidewalk]
    if len(walks) < 2:
        raise ValueError("SUMO network has fewer than two edges with sidewalks: cannot generate pedestrians")
    walk_ids = np.array([e.edge_id for e in walks])
    walk_p = np.array([e.length for e in walks])
    walk_km = walk_p.sum() / 1000.0
    walk_p /= walk_p.sum()
    n_initial = int(round(rng.uniform(*config.pedestrians_per_km) * walk_km))
    inflow = rng.uniform(*config.pedestrian_inflow_per_km_per_s) * walk_km
    departs = np.sort(
        np.concatenate([rng.uniform(0.0, 2.0, n_initial), _arrival_times(rng, inflow, duration)])
    )
    ped_types = [t.type_id for t in types if t.family == "ped"]
    persons = []
    for i, depart in enumerate(departs):
        start, goal = rng.choice(walk_ids, 2, replace=False, p=walk_p)
        persons.append(
            (
                float(depart),
                f'<person id="p{i}" type="{rng.choice(ped_types)}" depart="{depart:.1f}" departPos="random">'
                f'<walk from="{start}" to="{goal}" arrivalPos="random"/></person>',
            )
        )
    return persons


def write_demand(
    net: SumoNet, rng: np.random.Generator, duration: float, path: Path, config: DemandConfig
) -> list[AgentType]:
    """Write a SUMO route file with random vTypes, trips and walks over ``duration`` s; return the vTypes."""
    types = draw_agent_types(rng, config)
    agents = _vehicle_trips(net, rng, duration, config, types) + _pedestrian_walks(
        net, rng, duration, config, types
    )
    body = [line for _, line in sorted(agents, key=lambda item: item[0])]
    header = [_vtype_xml(t, rng) for t in types]
    path.write_text("<routes>\n" + "\n".join(header + body) + "\n</routes>\n")
    return types
