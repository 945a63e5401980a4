// The C++ half of the ns3-network plugin, compiled by cppyy at load time
// (caviar_plugins.ns3.simulator). ns-3 calls back into C++ only: sockets, traces and
// topology live here, and Python polls what happened after each Simulator::Run().
#include "ns3/core-module.h"
#include "ns3/internet-module.h"
#include "ns3/lte-module.h"
#include "ns3/mobility-module.h"
#include "ns3/network-module.h"
#include "ns3/point-to-point-module.h"
#include "ns3/propagation-loss-model.h"
#include "ns3/traffic-control-module.h"

#include <cerrno>
#include <csignal>
#include <cstdio>
#include <cstring>
#include <exception>
#include <map>
#include <mutex>
#include <string>
#include <sys/wait.h>
#include <unistd.h>
#include <vector>

namespace caviar_ns3
{
using namespace ns3;

// Every UDP packet starts with this: which image, which packet of it (little endian u32s).
constexpr uint32_t kHeaderBytes = 8;

inline void
PutU32(uint8_t* p, uint32_t v)
{
    for (int i = 0; i < 4; ++i)
    {
        p[i] = (v >> (8 * i)) & 0xff;
    }
}

inline uint32_t
GetU32(const uint8_t* p)
{
    return p[0] | (p[1] << 8) | (p[2] << 16) | (uint32_t(p[3]) << 24);
}

// The ground station's end of one UE's flow: records every arrival.
class Receiver
{
  public:
    Receiver(Ptr<Node> node, uint16_t port, bool tcp)
        : m_tcp(tcp)
    {
        m_socket = Socket::CreateSocket(node,
                                        tcp ? TcpSocketFactory::GetTypeId()
                                            : UdpSocketFactory::GetTypeId());
        m_socket->Bind(InetSocketAddress(Ipv4Address::GetAny(), port));
        if (tcp)
        {
            m_socket->Listen();
            m_socket->SetAcceptCallback(MakeNullCallback<bool, Ptr<Socket>, const Address&>(),
                                        MakeCallback(&Receiver::Accept, this));
        }
        else
        {
            m_socket->SetRecvCallback(MakeCallback(&Receiver::Read, this));
        }
    }

    void Accept(Ptr<Socket> s, const Address&)
    {
        s->SetRecvCallback(MakeCallback(&Receiver::Read, this));
        m_accepted.push_back(s);
    }

    void Read(Ptr<Socket> s)
    {
        Ptr<Packet> p;
        Address from;
        while ((p = s->RecvFrom(from)))
        {
            uint32_t image = 0;
            uint32_t index = 0;
            if (!m_tcp && p->GetSize() >= kHeaderBytes)
            {
                uint8_t h[kHeaderBytes];
                p->CopyData(h, kHeaderBytes);
                image = GetU32(h);
                index = GetU32(h + 4);
            }
            image_.push_back(image);
            index_.push_back(index);
            bytes_.push_back(p->GetSize());
            time_.push_back(Simulator::Now().GetSeconds());
        }
    }

    void Clear()
    {
        image_.clear();
        index_.clear();
        bytes_.clear();
        time_.clear();
    }

    std::vector<uint32_t> image_, index_, bytes_;
    std::vector<double> time_;

  private:
    bool m_tcp;
    Ptr<Socket> m_socket;
    std::vector<Ptr<Socket>> m_accepted;
};

// A UE's end: queues an image's bytes as UDP packets or into one TCP stream.
class Sender
{
  public:
    Sender(Ptr<Node> node, Ipv4Address dst, uint16_t port, bool tcp)
        : m_tcp(tcp)
    {
        m_socket = Socket::CreateSocket(node,
                                        tcp ? TcpSocketFactory::GetTypeId()
                                            : UdpSocketFactory::GetTypeId());
        m_socket->Bind();
        m_socket->Connect(InetSocketAddress(dst, port));
    }

    // Packets of `payload` image bytes (+ the 8-byte header) for UDP; returns the packets
    // sent. TCP: the bytes go into the stream; returns the bytes the socket accepted.
    uint32_t Send(uint32_t image, uint32_t nbytes, uint32_t payload)
    {
        if (m_tcp)
        {
            int sent = m_socket->Send(Create<Packet>(nbytes));
            return sent < 0 ? 0 : uint32_t(sent);
        }
        uint32_t n = (nbytes + payload - 1) / payload;
        std::vector<uint8_t> buf(payload + kHeaderBytes, 0);
        for (uint32_t k = 0; k < n; ++k)
        {
            uint32_t size = std::min(payload, nbytes - k * payload) + kHeaderBytes;
            PutU32(buf.data(), image);
            PutU32(buf.data() + 4, k);
            m_socket->Send(Create<Packet>(buf.data(), size));
        }
        return n;
    }

  private:
    bool m_tcp;
    Ptr<Socket> m_socket;
};

// Per-RNTI sums of the eNB's uplink traces over a step.
class UplinkStats
{
  public:
    void Sinr(uint16_t, uint16_t rnti, double sinr, uint8_t)
    {
        m_sinr[rnti] += sinr;
        m_sinrCount[rnti] += 1;
    }

    void Scheduled(uint32_t, uint32_t, uint16_t rnti, uint8_t mcs, uint16_t bytes, uint8_t)
    {
        m_mcs[rnti] += mcs;
        m_grants[rnti] += 1;
        m_tbBytes[rnti] += bytes;
        m_mcsHistogram[rnti][mcs] += 1;
    }

    double MeanSinr(uint16_t rnti) { return m_sinrCount[rnti] ? m_sinr[rnti] / m_sinrCount[rnti] : -1.0; }
    double MeanMcs(uint16_t rnti) { return m_grants[rnti] ? m_mcs[rnti] / m_grants[rnti] : -1.0; }
    uint32_t Grants(uint16_t rnti) { return m_grants[rnti]; }
    double TbBytes(uint16_t rnti) { return m_tbBytes[rnti]; }

    // The MCS granted most often over the step (-1: none).
    int ModeMcs(uint16_t rnti)
    {
        int best = -1;
        uint32_t most = 0;
        for (auto& [mcs, n] : m_mcsHistogram[rnti])
        {
            if (n > most)
            {
                most = n;
                best = mcs;
            }
        }
        return best;
    }

    void Clear()
    {
        m_sinr.clear();
        m_sinrCount.clear();
        m_mcs.clear();
        m_grants.clear();
        m_tbBytes.clear();
        m_mcsHistogram.clear();
    }

  private:
    std::map<uint16_t, double> m_sinr, m_mcs, m_tbBytes;
    std::map<uint16_t, uint32_t> m_sinrCount, m_grants;
    std::map<uint16_t, std::map<int, uint32_t>> m_mcsHistogram;
};

// One network: the UEs, the ground station behind it, and what connects them.
class Network
{
  public:
    NodeContainer ues, enbs, remote;
    NetDeviceContainer ueDevs, enbDevs;
    Ptr<LteHelper> lte;
    Ptr<MatrixPropagationLossModel> ulLoss, dlLoss;
    std::vector<Receiver*> receivers;
    std::vector<Sender*> senders;
    UplinkStats stats;

    ~Network()
    {
        for (auto* r : receivers)
        {
            delete r;
        }
        for (auto* s : senders)
        {
            delete s;
        }
    }

    void SetPosition(uint32_t ue, double x, double y, double z)
    {
        ues.Get(ue)->GetObject<MobilityModel>()->SetPosition(Vector(x, y, z));
    }

    void SetEnbPosition(double x, double y, double z)
    {
        enbs.Get(0)->GetObject<MobilityModel>()->SetPosition(Vector(x, y, z));
    }

    // The link's loss (dB) between UE `ue` and the cell, both directions.
    void SetLoss(uint32_t ue, double lossDb)
    {
        Ptr<MobilityModel> a = ues.Get(ue)->GetObject<MobilityModel>();
        Ptr<MobilityModel> b = enbs.Get(0)->GetObject<MobilityModel>();
        ulLoss->SetLoss(a, b, lossDb, true);
        if (dlLoss != ulLoss)
        {
            dlLoss->SetLoss(a, b, lossDb, true);
        }
    }

    // The transmit buffer (bytes) of UE `ue`'s UM RLC entities, its data radio bearers';
    // returns how many it set. LteRlcUm reads it as each packet arrives from PDCP.
    uint32_t SetRlcBuffer(uint32_t ue, uint32_t bytes)
    {
        ObjectMapValue drbs;
        DynamicCast<LteUeNetDevice>(ueDevs.Get(ue))->GetRrc()->GetAttribute("DataRadioBearerMap", drbs);
        uint32_t n = 0;
        for (auto it = drbs.Begin(); it != drbs.End(); ++it)
        {
            PointerValue rlc;
            it->second->GetAttribute("LteRlc", rlc);
            Ptr<LteRlcUm> um = DynamicCast<LteRlcUm>(rlc.Get<LteRlc>());
            if (um)
            {
                um->SetAttribute("MaxTxBufferSize", UintegerValue(bytes));
                ++n;
            }
        }
        return n;
    }

    uint16_t Rnti(uint32_t ue)
    {
        return DynamicCast<LteUeNetDevice>(ueDevs.Get(ue))->GetRrc()->GetRnti();
    }

    void AddFlows(bool tcp, uint16_t basePort)
    {
        Ipv4Address dst = remote.Get(0)->GetObject<Ipv4>()->GetAddress(1, 0).GetLocal();
        for (uint32_t i = 0; i < ues.GetN(); ++i)
        {
            if (!lte)
            {
                // point to point: the ground station's end of UE i's own link
                dst = remote.Get(0)->GetObject<Ipv4>()->GetAddress(i + 1, 0).GetLocal();
            }
            receivers.push_back(new Receiver(remote.Get(0), basePort + i, tcp));
            senders.push_back(new Sender(ues.Get(i), dst, basePort + i, tcp));
        }
    }
};

// LTE with its EPC: one eNB, the UEs, and the ground station behind the PGW over a
// point-to-point backhaul. Losses come from MatrixPropagationLossModel (set per step).
inline Network*
BuildLte(uint32_t nUes,
         uint16_t bandwidthRb,
         std::string scheduler,
         std::string backhaulRate,
         double backhaulDelay,
         double attachLossDb)
{
    auto* net = new Network();
    net->lte = CreateObject<LteHelper>();
    Ptr<PointToPointEpcHelper> epc = CreateObject<PointToPointEpcHelper>();
    net->lte->SetEpcHelper(epc);
    net->lte->SetAttribute("PathlossModel", StringValue("ns3::MatrixPropagationLossModel"));
    net->lte->SetSchedulerType(scheduler);
    net->lte->SetEnbDeviceAttribute("UlBandwidth", UintegerValue(bandwidthRb));
    net->lte->SetEnbDeviceAttribute("DlBandwidth", UintegerValue(bandwidthRb));

    Ptr<Node> pgw = epc->GetPgwNode();
    net->remote.Create(1);
    InternetStackHelper internet;
    internet.Install(net->remote);
    PointToPointHelper p2p;
    p2p.SetDeviceAttribute("DataRate", DataRateValue(DataRate(backhaulRate)));
    p2p.SetDeviceAttribute("Mtu", UintegerValue(1500));
    p2p.SetChannelAttribute("Delay", TimeValue(Seconds(backhaulDelay)));
    NetDeviceContainer backhaul = p2p.Install(pgw, net->remote.Get(0));
    Ipv4AddressHelper addresses;
    addresses.SetBase("1.0.0.0", "255.0.0.0");
    addresses.Assign(backhaul);
    Ipv4StaticRoutingHelper routing;
    routing.GetStaticRouting(net->remote.Get(0)->GetObject<Ipv4>())
        ->AddNetworkRouteTo(Ipv4Address("7.0.0.0"), Ipv4Mask("255.0.0.0"), 1);

    net->enbs.Create(1);
    net->ues.Create(nUes);
    MobilityHelper mobility;
    mobility.SetMobilityModel("ns3::ConstantPositionMobilityModel");
    mobility.Install(net->enbs);
    mobility.Install(net->ues);
    // Apart until the engine places them: the spectrum channel applies no loss at all
    // between two nodes at one point.
    net->SetEnbPosition(0, 0, 25);
    for (uint32_t i = 0; i < nUes; ++i)
    {
        net->SetPosition(i, 10.0 * (i + 1), 0, 1.5);
    }
    net->enbDevs = net->lte->InstallEnbDevice(net->enbs);
    net->ueDevs = net->lte->InstallUeDevice(net->ues);
    internet.Install(net->ues);
    epc->AssignUeIpv4Address(net->ueDevs);
    for (uint32_t i = 0; i < nUes; ++i)
    {
        routing.GetStaticRouting(net->ues.Get(i)->GetObject<Ipv4>())
            ->SetDefaultRoute(epc->GetUeDefaultGatewayAddress(), 1);
    }
    net->ulLoss = DynamicCast<MatrixPropagationLossModel>(
        net->lte->GetUplinkSpectrumChannel()->GetPropagationLossModel());
    net->dlLoss = DynamicCast<MatrixPropagationLossModel>(
        net->lte->GetDownlinkSpectrumChannel()->GetPropagationLossModel());
    for (uint32_t i = 0; i < nUes; ++i)
    {
        net->SetLoss(i, attachLossDb);
    }
    net->lte->Attach(net->ueDevs, net->enbDevs.Get(0));

    Ptr<LteEnbNetDevice> enb = DynamicCast<LteEnbNetDevice>(net->enbDevs.Get(0));
    enb->GetPhy()->TraceConnectWithoutContext("ReportUeSinr",
                                              MakeCallback(&UplinkStats::Sinr, &net->stats));
    enb->GetMac()->TraceConnectWithoutContext("UlScheduling",
                                              MakeCallback(&UplinkStats::Scheduled, &net->stats));
    return net;
}

// One point-to-point link per UE to the ground station: no radio, the reference case.
inline Network*
BuildP2p(uint32_t nUes, std::string rate, double delay, std::string queue)
{
    auto* net = new Network();
    net->remote.Create(1);
    net->ues.Create(nUes);
    InternetStackHelper internet;
    internet.Install(net->remote);
    internet.Install(net->ues);
    MobilityHelper mobility;
    mobility.SetMobilityModel("ns3::ConstantPositionMobilityModel");
    mobility.Install(net->ues);
    PointToPointHelper p2p;
    p2p.SetDeviceAttribute("DataRate", DataRateValue(DataRate(rate)));
    p2p.SetChannelAttribute("Delay", TimeValue(Seconds(delay)));
    p2p.SetQueue("ns3::DropTailQueue<Packet>", "MaxSize", QueueSizeValue(QueueSize(queue)));
    Ipv4AddressHelper addresses;
    for (uint32_t i = 0; i < nUes; ++i)
    {
        NetDeviceContainer link = p2p.Install(net->ues.Get(i), net->remote.Get(0));
        std::string base = "10." + std::to_string(i / 256) + "." + std::to_string(i % 256) + ".0";
        addresses.SetBase(base.c_str(), "255.255.255.0");
        addresses.Assign(link);
        // Assign installs ns-3's default queue disc (FqCoDel), which would queue (and drop)
        // ahead of the device: the device's DropTail queue is the only queue.
        TrafficControlHelper tch;
        tch.Uninstall(link);
    }
    return net;
}

// The value type of an attribute ("ns3::DoubleValue"), "" if there is no such attribute.
inline std::string
AttributeType(std::string path)
{
    auto pos = path.rfind("::");
    if (pos == std::string::npos)
    {
        return "";
    }
    TypeId tid;
    if (!TypeId::LookupByNameFailSafe(path.substr(0, pos), &tid))
    {
        return "";
    }
    TypeId::AttributeInformation info;
    if (!tid.LookupAttributeByName(path.substr(pos + 2), &info))
    {
        return "";
    }
    return info.checker->GetValueTypeName();
}

// Keeps the last characters written to std::cerr, passing them on (or holding them back
// meanwhile): ns-3 writes why it aborts there just before it does (NS_FATAL_ERROR, NS_ASSERT).
class ErrTail : public std::streambuf
{
  public:
    explicit ErrTail(std::streambuf* out)
        : m_out(out)
    {
    }

    std::streambuf* Out()
    {
        return m_out;
    }

    // Holds back what is written until Hold(false) passes it on (or Drop() drops it);
    // meanwhile std::terminate aborts without libstdc++'s words.
    void Hold(bool on)
    {
        std::lock_guard<std::mutex> lock(m_mutex);
        m_hold = on;
        if (on)
        {
            m_terminate = std::set_terminate([] { std::abort(); });
        }
        else
        {
            std::set_terminate(m_terminate);
            Pass();
        }
    }

    void Drop()
    {
        std::lock_guard<std::mutex> lock(m_mutex);
        m_pending.clear();
    }

    uint64_t Written()
    {
        std::lock_guard<std::mutex> lock(m_mutex);
        return m_written;
    }

    // What was written since Written() returned `mark` (at most the last 16 kB).
    std::string Since(uint64_t mark)
    {
        std::lock_guard<std::mutex> lock(m_mutex);
        uint64_t n = std::min<uint64_t>(m_written - std::min(mark, m_written), m_text.size());
        return m_text.substr(m_text.size() - n);
    }

  protected:
    int overflow(int c) override
    {
        if (c == EOF)
        {
            return 0;
        }
        char ch = char(c);
        Keep(&ch, 1);
        return c;
    }

    std::streamsize xsputn(const char* s, std::streamsize n) override
    {
        Keep(s, n);
        return n;
    }

    int sync() override
    {
        return m_out->pubsync();
    }

  private:
    void Keep(const char* s, std::streamsize n)
    {
        std::lock_guard<std::mutex> lock(m_mutex);
        m_text.append(s, n);
        m_written += n;
        if (m_text.size() > 16384)
        {
            m_text.erase(0, m_text.size() - 16384);
        }
        m_pending.append(s, n);
        if (!m_hold || m_pending.size() > 65536)
        {
            Pass();
        }
    }

    void Pass()
    {
        if (!m_pending.empty())
        {
            m_out->sputn(m_pending.data(), m_pending.size());
            m_out->pubsync();
            m_pending.clear();
        }
    }

    std::streambuf* m_out;
    std::mutex m_mutex;
    std::string m_text, m_pending;
    uint64_t m_written = 0;
    bool m_hold = false;
    std::terminate_handler m_terminate = nullptr;
};

// std::cerr (and std::clog, where ns-3 writes the time before a fatal error's file and
// line) through an ErrTail, once per process; returns it.
inline ErrTail*
Errors()
{
    static ErrTail* tail = [] {
        auto* t = new ErrTail(std::cerr.rdbuf());
        std::cerr.rdbuf(t);
        std::clog.rdbuf(t);
        return t;
    }();
    return tail;
}

// What ns-3 says of `value` for attribute `path` ("ns3::PointToPointNetDevice::DataRate"):
// "" if it takes it, else its own words. ns-3 aborts the process on some values it cannot
// parse (an enum name it does not know, a time or a rate it cannot read): the parse runs in
// a child process (fork) that writes nothing but into a pipe and never returns here.
inline std::string
CheckValue(std::string path, std::string value)
{
    auto pos = path.rfind("::");
    TypeId tid;
    TypeId::AttributeInformation info;
    if (pos == std::string::npos || !TypeId::LookupByNameFailSafe(path.substr(0, pos), &tid) ||
        !tid.LookupAttributeByName(path.substr(pos + 2), &info))
    {
        return "ns-3 has no such attribute";
    }
    int fds[2];
    if (pipe(fds) != 0)
    {
        return "cannot check it: pipe() failed";
    }
    std::fflush(nullptr);
    pid_t pid = fork();
    if (pid == 0)
    {
        for (int sig : {SIGABRT, SIGSEGV, SIGBUS, SIGILL, SIGFPE, SIGTRAP})
        {
            std::signal(sig, SIG_DFL); // no interpreter's crash handler (it would run gdb)
        }
        dup2(fds[1], 1);
        dup2(fds[1], 2);
        close(fds[0]);
        std::cerr.rdbuf(Errors()->Out()); // straight to the pipe, never held back
        bool ok = info.checker->CreateValidValue(StringValue(value)) != nullptr;
        std::cerr.flush();
        _exit(ok ? 0 : 3);
    }
    close(fds[1]);
    if (pid < 0)
    {
        close(fds[0]);
        return "cannot check it: fork() failed";
    }
    std::string said;
    char buf[4096];
    ssize_t n;
    while ((n = read(fds[0], buf, sizeof buf)) > 0 || (n < 0 && errno == EINTR))
    {
        said.append(buf, n > 0 ? n : 0);
    }
    close(fds[0]);
    int status = 0;
    while (waitpid(pid, &status, 0) < 0 && errno == EINTR)
    {
    }
    if (WIFEXITED(status) && WEXITSTATUS(status) == 0)
    {
        return "";
    }
    return said.empty() ? std::string("it does not parse") : said;
}

// The types ns-3 can build that derive from `base`, comma-separated ("ns3::PfFfMacScheduler,...").
inline std::string
ChildrenOf(std::string base)
{
    TypeId parent = TypeId::LookupByName(base);
    std::string out;
    for (uint16_t i = 0; i < TypeId::GetRegisteredN(); ++i)
    {
        TypeId tid = TypeId::GetRegistered(i);
        if (tid != parent && tid.IsChildOf(parent) && tid.HasConstructor())
        {
            out += (out.empty() ? "" : ",") + tid.GetName();
        }
    }
    return out;
}

// A rate CheckValue took ("10Mbps"), in bit/s.
inline double
RateBps(std::string rate)
{
    return double(DataRate(rate).GetBitRate());
}

// Sets an attribute's default ("ns3::LteUePhy::TxPower"); false if no such attribute or
// the value does not parse.
inline bool
SetDefault(std::string name, std::string value)
{
    return Config::SetDefaultFailSafe(name, StringValue(value));
}

// Everything a later network in this process must not inherit.
inline void
Reset()
{
    Simulator::Destroy();
    Ipv4AddressGenerator::Reset();
    Config::Reset();
}

} // namespace caviar_ns3
