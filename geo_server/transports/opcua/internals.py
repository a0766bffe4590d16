"""What the OPC UA interface uses of asyncua beyond its public API, in one place (docs/
design.md §9.1).

asyncua's `Server` has no public way to answer a node's reads from elsewhere, to send one
sample to many monitored items without a deep copy per item, or to refuse monitored items
past a limit: the interface (server.py) does it through asyncua's internal server, its
address space, services and subscriptions, reached only through the functions here.
The guard in front of asyncua's transport and sessions (guard.py) is the other module
that knows asyncua's internals; tests/test_opcua_internals.py checks that no third module
of geo_server reaches `iserver`, `aspace`, `_monitored_items` and the like.

`RELIED_ON` holds the sha256 of the source of every asyncua function whose behaviour
these two modules, server.py and monitoring.py depend on, hook or re-implement
(`datachange_callback`: `monitoring.Monitoring._notify`); tests/test_opcua_internals.py
fails on an asyncua where one of them changed (or moved), so that each use is looked at
again before the pin moves.
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import inspect
from collections.abc import Callable
from typing import Any, NamedTuple

#: The asyncua these internals were read from (pyproject.toml pins >=2.1,<3).
ASYNCUA = "2.1.0"

#: "module:qualified name" -> sha256 of its source, as asyncua 2.1.0 has it.
RELIED_ON: dict[str, str] = {
    # guard.py: `start` copies it with the guarded transport
    "asyncua.server.server:Server.start": (
        "0e7d0b97d12c9075cbbca20bf115f77b371aab02997bc61bb302b607755b6579"
    ),
    # guard.py: the transport it subclasses
    "asyncua.server.binary_server_asyncio:BinaryServer._make_protocol": (
        "5c0c260fe64faf4d43332947c014636a4acf361ac269ee49a2cbb26181cd1976"
    ),
    "asyncua.server.binary_server_asyncio:OPCUAProtocol.connection_made": (
        "67ce5af61202da4f182b64338e3396e63163c11010dfb4e14fd1472e99132e4b"
    ),
    "asyncua.server.binary_server_asyncio:OPCUAProtocol.connection_lost": (
        "f5e287852bda01095f428c633e10e37a6c9e3e1832fa1990aea642027f791d58"
    ),
    "asyncua.server.binary_server_asyncio:OPCUAProtocol.data_received": (
        "bacb98f07f0b63ff2d74c3e485602ee59deec813e1593425dc000d5a15b98112"
    ),
    "asyncua.server.binary_server_asyncio:OPCUAProtocol._process_one_msg": (
        "c2162392f00a7272279f8f71acb19c6669bf00e9cc211aad54a18503460e417c"
    ),
    "asyncua.server.uaprocessor:UaProcessor._should_close_session_on_transport_loss": (
        "612283235d5dc17ceb9601d21c9fb312aabaf4dea5bb13c1d2806b15ca512823"
    ),
    "asyncua.server.uaprocessor:UaProcessor._process_message": (
        "029ff357dd3bdd16a53eec2a830fdc0660d2c1736123715255f7e3dead8ae11b"
    ),
    # guard.py: the sessions it hooks
    "asyncua.server.internal_server:InternalServer.__init__": (
        "9a151b9f9c85021db0a349f375b083dcddbca22415d3b4ebf9481d7b6ebdec1e"
    ),
    "asyncua.server.internal_server:InternalServer.create_session": (
        "20ddcc7f3bf23d2b79b324221f1e1e4e4fc650e7b3ba0fd3e6cc116d51d4f96c"
    ),
    "asyncua.server.internal_server:InternalServer.register_external_session": (
        "c78e1de5967c64b9289d470e2028b2f1b475e1928a78a0b0c8947029d57ae5ce"
    ),
    "asyncua.server.internal_server:InternalServer.unregister_external_session": (
        "b57afce91b201df64262bd605aa61cb59bb18d892b4683cbedc986386bdcf71e"
    ),
    "asyncua.server.internal_server:InternalServer.lookup_external_session": (
        "93f4ee60c93a33b1562b395cec15056375860c6267e55ba827ce144ccd9220b1"
    ),
    "asyncua.server.internal_server:InternalServer.start": (
        "46457dca494d2a1fb4383ab021526dc236ff948b037a7501156610fbd3f45f97"
    ),
    "asyncua.server.internal_server:InternalServer.stop": (
        "1f47ced4d372bb4870b844f5d01d03ecfe756643cc12e10737b9d7694c6ea625"
    ),
    "asyncua.server.internal_session:InternalSession.activate_session": (
        "cfe664a2bb572c9ffecfc1339759eadadec32eb82fc69df940a043019d9948fd"
    ),
    "asyncua.server.internal_session:InternalSession.close_session": (
        "e49eeda62b56742c34345c0dd001432f562e1789415fcf47c10cb132beecdd94"
    ),
    "asyncua.server.internal_session:InternalSession.create_subscription": (
        "3cc1876d55cae81051f1ebd0d504208a2a8d16bf550cef69d23485818caeafdc"
    ),
    "asyncua.server.internal_session:InternalSession.create_monitored_items": (
        "65301bafcb5825018c9a94e807e1c4c2a2b4c58c2b9de990933c08ee1df76465"
    ),
    "asyncua.server.internal_session:InternalSession.modify_monitored_items": (
        "0c2f3304cc21507db19e712baf1299d401261f09bd3f03432a0e5cb4c39c853d"
    ),
    "asyncua.server.internal_session:InternalSession.delete_subscriptions": (
        "10d6506b7bffb0bd9132c75081fe5486ff13449ea2f5af3103ce7a2be72bb981"
    ),
    "asyncua.server.internal_session:InternalSession.set_publishing_mode": (
        "f3acfdc7b453fc5a0e58f8c99369be0e856fcc0f09faef954809515c7e779067"
    ),
    # server.py through this module: the services it hooks, the address space it serves
    "asyncua.server.address_space:AddressSpace.__init__": (
        "5560020cb1d464925ead82bec01782a05354e4f7c150ccf68ba065591ff8e038"
    ),
    "asyncua.server.address_space:AddressSpace.add_datachange_callback": (
        "afb2b5eeec48d3328f97959c79043ac16ed5861e81acdc7b4cffbf3c0091517d"
    ),
    "asyncua.server.address_space:AddressSpace.delete_datachange_callback": (
        "f1b970017dd746579caf0a603ecac82fadb20a19a139bd03dc1e669326f7acbf"
    ),
    "asyncua.server.address_space:AddressSpace.read_attribute_value": (
        "836c43c0cc2d4b0191a9937d42f7b8060308ecd96738b0789aa60d17d3aa9d99"
    ),
    "asyncua.server.address_space:AddressSpace.set_attribute_value_callback": (
        "2ca2f7fb31a3dc79df9ddd7d1809a16ead14a09914d18a529c982adb02905d0d"
    ),
    "asyncua.server.address_space:AddressSpace.set_attribute_value_setter": (
        "1b8fdf584e8a115768074bd4d9dfb8dc32b28c4585c34825be3e664481f1baef"
    ),
    "asyncua.server.address_space:AddressSpace.add_method_callback": (
        "d0977caaa39ab5e737992f551b430653a4197ed2fb215e6511e2feddef646c4f"
    ),
    "asyncua.server.address_space:AttributeService.read": (
        "b9b9b6a27cf43cc9a88f69e2cdbf644ea95c81e8e551d0d67e4479477947ac62"
    ),
    "asyncua.server.address_space:AttributeService.write": (
        "5a6028729a9239e7d174190c3b3c8a3b05146fc3989d405121d4fcdebf047d9e"
    ),
    "asyncua.server.address_space:MethodService.call": (
        "caea17f731bb46b7b8e05ade74eac54eb9f54602402eee1871c6a7e6d13df430"
    ),
    "asyncua.server.address_space:NodeManagementService.add_nodes": (
        "7b24f18a8c6b6957b34818090d10071cd4a937a3d9ca58a32a4dee0e06e65f47"
    ),
    "asyncua.server.subscription_service:SubscriptionService.create_monitored_items": (
        "6d8b5e7c1eb9496bd1dec0b947953ac2097d141a2dfd91bacf31b9d7a5b72244"
    ),
    "asyncua.server.subscription_service:SubscriptionService.modify_monitored_items": (
        "f1196c7dae448ee92896a816a3835ce34b51fbde44bcb83a27e0194673a1a143"
    ),
    "asyncua.server.subscription_service:SubscriptionService.set_monitoring_mode": (
        "226c05d5517c85fa85605f0804018891b71df1c2e25853851f80d23805eefe68"
    ),
    # monitoring.py: `_notify` does what `datachange_callback` does, without its copy per item
    "asyncua.server.monitored_item_service:MonitoredItemService.__init__": (
        "6179ce8fbf4dddb33e19f3e5f16b19345e529e2771cd7a87c37814f8b8dd0238"
    ),
    "asyncua.server.monitored_item_service:MonitoredItemService.datachange_callback": (
        "d4468698f4d16058fe297b56f9900b9cd5883027bda8c94ce90b724c9045ea3b"
    ),
    "asyncua.server.monitored_item_service:MonitoredItemService.trigger_datachange": (
        "22d2c0264f30e62b99507e8c7d2d709b200d4f867293917d997f1b3a6838f055"
    ),
    "asyncua.server.internal_subscription:InternalSubscription.enqueue_datachange_event": (
        "83acd6e086d9b1c9a22db83708576fb56fd61d42c85b0ade5c9c75d7650c1928"
    ),
    # (guard.py: each period's publishing looked up on the instance, and hooked there)
    "asyncua.server.internal_subscription:InternalSubscription.publish_results": (
        "61ce721eff3735ea0af1220d5e9b8691fb05a99bb488685fec4ff3cf88ad3818"
    ),
    "asyncua.server.internal_subscription:InternalSubscription._subscription_loop": (
        "3a0267cf3db3e20ff3f084539e6b427c006ff72c81ff20071c6e995952781f00"
    ),
    "asyncua.server.internal_subscription:InternalSubscription._trigger_publish": (
        "ef1353aab64eccc0e08e6648c12a3b3bf4612f15519e0f8a42caf03da834dba6"
    ),
    "asyncua.server.uaprocessor:UaProcessor.forward_publish_response": (
        "9e380500dd66b1721a6c54b22293c6e54bb2b5603d99491eadf6f3be54900f10"
    ),
}


def ua() -> Any:
    """asyncua's `ua` module (its public types), imported when first needed: server.py
    and monitoring.py import without asyncua. Typed as Any: its stubs type numbers as
    NewTypes (`Int16`, `UInt32`) that plain ints do not satisfy."""
    from asyncua import ua as module

    return module


def source_hash(where: str) -> str:
    """sha256 of the source of `where` ("module:Qualified.name") in the asyncua
    installed; "" when it is not there."""
    module_name, _, qualified = where.partition(":")
    try:
        obj: Any = importlib.import_module(module_name)
        for part in qualified.split("."):
            obj = getattr(obj, part)
        source = inspect.getsource(obj)
    except (ImportError, AttributeError, OSError, TypeError):
        return ""
    return hashlib.sha256(source.encode()).hexdigest()


def changed() -> list[str]:
    """The functions of `RELIED_ON` that differ in the asyncua installed."""
    return [where for where, digest in RELIED_ON.items() if source_hash(where) != digest]


# ---------------------------------------------------------------------- the server


def set_limits(server: Any, connections: int, subscriptions: int) -> None:
    """The internal server's caps of connections and of subscriptions in all sessions
    (`Server` sets them only from its constructor's defaults)."""
    iserver = server.iserver
    iserver.max_connections = connections
    iserver.max_subscriptions = subscriptions


def address_space(server: Any) -> Any:
    """The internal server's `AddressSpace`: node data by `NodeId` (`[...]`, `in`,
    `keys`), each with its `attributes` (by `AttributeIds`) and `references`; value
    callbacks and setters per node; method callbacks."""
    return server.iserver.aspace


def nodes(server: Any) -> dict[Any, Any]:
    """The address space's node data by `NodeId`, as the dict it keeps (a NodeSet import
    is compared and restored through it: companions.py)."""
    held: dict[Any, Any] = server.iserver.aspace._nodes
    return held


def add_nodes(server: Any, items: list[Any]) -> list[Any]:
    """AddNodes as the server's own session, without a request per node."""
    results: list[Any] = server.iserver.isession.iserver.node_mgt_service.add_nodes(items)
    return results


class Services(NamedTuple):
    """The internal server's services the interface hooks (their methods replaced on
    this server's instances only)."""

    attribute: Any  # read, write
    method: Any  # call
    subscription: Any  # create_monitored_items, modify_monitored_items, set_monitoring_mode


def services(server: Any) -> Services:
    iserver = server.iserver
    return Services(iserver.attribute_service, iserver.method_service, iserver.subscription_service)


# ---------------------------------------------------------------------- subscriptions


def subscriptions(server: Any) -> dict[int, Any]:
    """Every session's subscriptions by id (`session_id` names the session of each)."""
    subs: dict[int, Any] = server.iserver.subscription_service.subscriptions
    return subs


def monitored_items(sub: Any) -> dict[int, Any]:
    """A subscription's monitored items by id ({} for no subscription): each with its
    `mode`, `callback_handle`, `read_value_id`, `client_handle`, `queue_size` and
    `mvalue` (the values last sampled)."""
    if sub is None:
        return {}
    items: dict[int, Any] = sub.monitored_item_srv._monitored_items
    return items


async def trigger_datachange(sub: Any, handle: int, node_id: Any, attribute: Any) -> None:
    """Sample the node of item `handle` of `sub` now, as asyncua does for a new item."""
    await sub.monitored_item_srv.trigger_datachange(handle, node_id, attribute)


def callbacks_of(attval: Any) -> list[tuple[int, Callable[..., Any]]]:
    """The data-change callbacks of a node's attribute (`AttributeValue`), by handle."""
    return list(attval.datachange_callbacks.items())


class Target(NamedTuple):
    """A monitored item a data-change callback notifies (`item_of`)."""

    owner: Any  # its subscription's MonitoredItemService
    mid: int
    item: Any


def item_of(callback: Callable[..., Any], handle: int) -> Target | None:
    """The monitored item `callback` (asyncua's `MonitoredItemService.datachange_
    callback`, bound) notifies for `handle`; None while it is being made or deleted, or
    for a callback of anything else."""
    owner: Any = getattr(callback, "__self__", None)  # (a bound method's: asyncua's)
    if not isinstance(owner, _monitored_item_service()):
        return None
    mid = owner._monitored_datachange.get(handle)
    item = owner._monitored_items.get(mid) if mid is not None else None
    return None if mid is None or item is None else Target(owner, mid, item)


async def enqueue(target: Target, note: Any) -> None:
    """Queue the notification `note` of `target` for its subscription, at most the
    item's queue size (what `datachange_callback` does after its copy of the value)."""
    isub = target.owner.isub
    await isub.enqueue_datachange_event(target.mid, note, target.item.queue_size)


@functools.cache
def _monitored_item_service() -> Any:
    """asyncua's `MonitoredItemService`, imported when first needed (once): server.py
    imports this module, and importing it loads no asyncua (the plug reads its options
    class before OPC UA's start imports asyncua off the loop)."""
    from asyncua.server.monitored_item_service import MonitoredItemService

    return MonitoredItemService


def attribute_value(data_value: Any) -> Any:
    """A node attribute's holder (`AttributeValue`) for `data_value`."""
    from asyncua.server.address_space import AttributeValue

    return AttributeValue(data_value)


def node_data(node_id: Any) -> Any:
    """An empty node's data (`NodeData`) for `node_id`, to fill and put in the address
    space."""
    from asyncua.server.address_space import NodeData

    return NodeData(node_id)
